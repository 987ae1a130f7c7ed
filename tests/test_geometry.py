"""The one angle-wrap and clip helpers (issue 14: five copies of wrap_angle before)."""

import math

import numpy as np

from leafgate.geometry import clip, clip_abs, wrap_angle


def test_wrap_angle_scalar_range_and_identity() -> None:
    assert wrap_angle(0.0) == 0.0
    assert wrap_angle(math.pi) == -math.pi  # [−π, π): +π maps to −π
    assert math.isclose(wrap_angle(3.0 * math.pi / 2.0), -math.pi / 2.0)
    assert math.isclose(wrap_angle(-7.0), -7.0 + 2.0 * math.pi)
    assert isinstance(wrap_angle(1.0), float)


def test_wrap_angle_array_matches_scalar() -> None:
    angles = np.linspace(-20.0, 20.0, 401)
    wrapped = wrap_angle(angles)
    assert wrapped.shape == angles.shape
    assert np.all(wrapped >= -math.pi) and np.all(wrapped < math.pi)
    assert [wrap_angle(float(a)) for a in angles] == wrapped.tolist()


def test_clip_helpers() -> None:
    assert clip_abs(3.0, 2.0) == 2.0
    assert clip_abs(-3.0, 2.0) == -2.0
    assert clip_abs(0.5, 2.0) == 0.5
    assert clip(5.0, -1.0, 4.0) == 4.0
    assert clip(-5.0, -1.0, 4.0) == -1.0
    assert clip(1.5, -1.0, 4.0) == 1.5
