"""Output that a flood of bad input cannot turn into a flood: log lines, STATUSTEXTs.

``Throttle``: the first occurrence passes at once; after that at most one per ``interval_s`` of the caller's clock
(the service clock, so tests drive it and simulated time keeps its meaning), and the one that passes carries how
many were held back since the previous one. ``RateLimitedLog`` is a log line so throttled (WARNING unless told),
carrying ``unlogged``; the occurrences not logged go to DEBUG.
"""

from __future__ import annotations

import logging
import math
from typing import Any

__all__ = ["RateLimitedLog", "Throttle"]


class Throttle:
    """``allow(now_s)`` for each occurrence; see the module docstring."""

    def __init__(self, interval_s: float) -> None:
        if not (math.isfinite(interval_s) and interval_s > 0.0):
            msg = f"interval_s must be finite and > 0, got {interval_s!r}"
            raise ValueError(msg)
        self.interval_s = interval_s
        self.held = 0  # occurrences held back since the last one that passed
        self.passed = 0  # occurrences that passed
        self._last_s: float | None = None

    def allow(self, now_s: float) -> int | None:
        """One occurrence at ``now_s`` [s]: None when it is held back, else how many were held back before it."""
        if self._last_s is not None and now_s - self._last_s < self.interval_s:
            self.held += 1
            return None
        held, self.held = self.held, 0
        self._last_s = now_s
        self.passed += 1
        return held


class RateLimitedLog:
    """``note(now_s, **extra)`` for each occurrence of ``event``; logs at ``level`` (WARNING by default) as described
    in the module docstring."""

    def __init__(self, logger: logging.Logger, event: str, interval_s: float, *, level: int = logging.WARNING) -> None:
        self._log = logger
        self.event = event
        self.level = level
        self._throttle = Throttle(interval_s)
        self.interval_s = interval_s

    @property
    def unlogged(self) -> int:
        """Occurrences since the last line at ``level`` that it did not carry."""
        return self._throttle.held

    @property
    def lines(self) -> int:
        """Lines written at ``level``."""
        return self._throttle.passed

    def note(self, now_s: float, **extra: Any) -> bool:
        """One occurrence at ``now_s`` [s]; True when it was logged at ``level``."""
        held = self._throttle.allow(now_s)
        if held is None:
            self._log.debug(self.event, extra=extra)
            return False
        self._log.log(self.level, self.event, extra={**extra, "unlogged": held})
        return True
