"""A log-line budget for the loop's modules that must not import the wire library (the
controllers and their helpers: tests/test_imports.py)."""

from __future__ import annotations

import time

__all__ = ["RateLimit"]


class RateLimit:
    """Lets through at most ``per_second`` events in each one-second window (a flood of bad
    inputs must not flood the log); the rest are counted in ``suppressed``."""

    __slots__ = ("_left", "_since", "per_second", "suppressed")

    def __init__(self, per_second: int = 10) -> None:
        self.per_second = per_second
        self._left = 0
        self._since = -1e9
        self.suppressed = 0

    def allow(self) -> bool:
        t = time.monotonic()
        if t - self._since >= 1.0:
            self._since, self._left = t, self.per_second
        if self._left <= 0:
            self.suppressed += 1
            return False
        self._left -= 1
        return True
