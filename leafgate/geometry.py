"""Small numeric helpers every layer uses: angle wrapping and clipping (SI units, rad).

One definition each, so the controller, the gateway's engage check, the simulator's metrics and
the baselines wrap and clip the same way.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np
import numpy.typing as npt

_TWO_PI = 2.0 * math.pi


@overload
def wrap_angle(angle: float) -> float: ...
@overload
def wrap_angle(angle: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def wrap_angle(angle: float | npt.NDArray[np.float64]) -> float | npt.NDArray[np.float64]:
    """Angle (scalar or array) wrapped to [−π, π), rad."""
    return (angle + math.pi) % _TWO_PI - math.pi


def clip(value: float, lo: float, hi: float) -> float:
    """``value`` limited to ``[lo, hi]``."""
    return lo if value < lo else hi if value > hi else value


def clip_abs(value: float, limit: float) -> float:
    """``value`` limited to ``[−limit, limit]``."""
    return min(max(value, -limit), limit)
