"""A WARNING that a flood of bad input cannot turn into a flood of log lines.

The first occurrence is logged at once; after that at most one line per ``interval_s`` of the caller's clock (the
service clock, so tests drive it and simulated time keeps its meaning), carrying ``unlogged``: how many
occurrences since the previous line were not logged. The ones not logged go to DEBUG.
"""

from __future__ import annotations

import logging
import math
from typing import Any

__all__ = ["RateLimitedWarning"]


class RateLimitedWarning:
    """``note(now_s, **extra)`` for each occurrence of ``event``; logs as described in the module docstring."""

    def __init__(self, logger: logging.Logger, event: str, interval_s: float) -> None:
        if not (math.isfinite(interval_s) and interval_s > 0.0):
            msg = f"interval_s must be finite and > 0, got {interval_s!r}"
            raise ValueError(msg)
        self._log = logger
        self.event = event
        self.interval_s = interval_s
        self.unlogged = 0  # occurrences since the last WARNING line that it did not carry
        self.lines = 0  # WARNING lines written
        self._last_s: float | None = None

    def note(self, now_s: float, **extra: Any) -> bool:
        """One occurrence at ``now_s`` [s]; True when it was logged at WARNING."""
        if self._last_s is not None and now_s - self._last_s < self.interval_s:
            self.unlogged += 1
            self._log.debug(self.event, extra=extra)
            return False
        self._log.warning(self.event, extra={**extra, "unlogged": self.unlogged})
        self._last_s = now_s
        self.unlogged = 0
        self.lines += 1
        return True
