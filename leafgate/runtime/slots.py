"""The latest-value slot: the newest sample of one input, shared between the thread that
receives it (python-can's Notifier, a Zenoh callback) and the control loop.

One class for every input (there were two, with different locking): writers serialise
through a lock, readers take none.
"""

from __future__ import annotations

import threading
from typing import Generic, TypeVar

from leafgate.messages import Stamped

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """The newest sample of one input, shared between a receiving thread and the control loop.

    Writers (receiving threads) serialise through a lock; readers take no lock: replacing the
    reference to an immutable :class:`~leafgate.messages.Stamped` is atomic, so a reader sees
    either the previous or the new sample, never a mix.
    """

    def __init__(self, key: str = "") -> None:
        self.key = key
        self._latest: Stamped[T] | None = None
        self._lock = threading.Lock()
        self._received = 0
        self._invalid = 0
        self._errors = 0
        self._last_error = ""

    def get(self) -> Stamped[T] | None:
        """The newest decoded sample with its receive time, or None before the first one."""
        return self._latest

    def put(self, sample: Stamped[T]) -> None:
        """Replace the newest sample (called by the subscriber)."""
        with self._lock:
            self._latest = sample
            self._received += 1
            if not sample.valid:
                self._invalid += 1

    def count_error(self, reason: str) -> None:
        """Count a payload that was dropped; the newest good sample stays."""
        with self._lock:
            self._errors += 1
            self._last_error = reason

    @property
    def received(self) -> int:
        """Samples decoded and stored so far."""
        return self._received

    @property
    def invalid(self) -> int:
        """Samples decoded but stored marked invalid (not finite, no points); in ``received``."""
        return self._invalid

    @property
    def errors(self) -> int:
        """Payloads dropped because they did not decode."""
        return self._errors

    @property
    def last_error(self) -> str:
        """Why the last dropped payload was dropped ("" if none was)."""
        return self._last_error
