"""The autopilot's clock against the receive clock, tracked over a stream of accepted poses.

Each pose's clock *offset* is its stamp (``time_boot_ms`` [s]) minus its receive time (service clock [s]). For the
autopilot's own stream the offset is a constant minus the link delay, plus a slow drift of the two clocks: a pose can
arrive late (a lower offset), never early. The *relation* is the offset of the least-delayed poses. ArduPilot
corrects offboard timestamps the same way (libraries/AP_RTC/JitterCorrection.cpp: "the data did not come from the
future", the offset of the packet with the least lag, re-converged over a window for drift), but it trusts its
sender: one sample that looks earlier moves its estimate at once. Here any pose may be forged, so:

- the relation is the ``CLOCK_RANK``-th highest offset of the accepted poses received in the last
  ``CLOCK_WINDOW_S`` (by time, so a flood of forged poses cannot push the genuine ones out), never fewer than
  ``CLOCK_RANK`` samples kept (a silent link keeps the last relation): one forged sample does not move it;
- it rises above a *floor* by at most ``budget_s`` (``safety.pose_time_jump_s``), and the floor follows the
  relation up by at most ``DRIFT_S_PER_S`` (down at once): poses stamped ahead can gain at most the budget in all,
  plus 1 ms per second, however many there are. A delay that shrinks for good by less than the budget (a drained
  queue) is learned at once; the budget then comes back as the floor follows.
"""

from __future__ import annotations

import collections
import heapq

__all__ = ["CLOCK_RANK", "CLOCK_WINDOW_S", "DRIFT_S_PER_S", "ClockRelation"]

CLOCK_WINDOW_S = 5.0  # accepted poses received this long ago still count [s]
CLOCK_RANK = 3  # the relation is the 3rd-highest offset in the window
CLOCK_MAX_SAMPLES = 1024  # at most this many (a flood of 1000 accepted poses a second still leaves 1 s of them)
# The floor's rise [s/s]: ten times a crystal's tolerance plus NTP's largest slew of the companion's clock (500 ppm).
DRIFT_S_PER_S = 1e-3


class ClockRelation:
    """Offsets in, the relation ``base_s`` out (see the module docstring)."""

    def __init__(self, budget_s: float) -> None:
        self.budget_s = budget_s
        self.base_s = 0.0  # stamp minus receive time of the least-delayed poses [s]
        # (receive time, offset) [s] of the accepted poses, oldest first
        self._samples: collections.deque[tuple[float, float]] = collections.deque(maxlen=CLOCK_MAX_SAMPLES)
        self._floor_s = 0.0
        self._floor_rx_s = 0.0

    def restart(self, samples: list[tuple[float, float]]) -> None:
        """A new time base or stream (the first pose, a reboot, a re-anchor on a candidate track): (receive time,
        offset) pairs [s], oldest first; the relation is taken from them alone."""
        self._samples.clear()
        self._samples.extend(samples)
        self._floor_s = self._rank()
        self._floor_rx_s = samples[-1][0]
        self.base_s = self._floor_s

    def add(self, rx_s: float, offset_s: float) -> None:
        """An accepted pose received at ``rx_s`` with clock offset ``offset_s`` [s]."""
        s = self._samples
        s.append((rx_s, offset_s))
        while len(s) > CLOCK_RANK and s[0][0] < rx_s - CLOCK_WINDOW_S:
            s.popleft()
        target = self._rank()
        rise = DRIFT_S_PER_S * max(0.0, rx_s - self._floor_rx_s)
        self._floor_s = min(target, self._floor_s + rise)
        self._floor_rx_s = rx_s
        self.base_s = min(target, self._floor_s + self.budget_s)

    def latest_stamp_s(self, rx_s: float) -> float:
        """The latest stamp [s] a pose received at ``rx_s`` can carry under the relation: its effective time is its
        stamp, but no later than this (perception/plausibility.py, "Time")."""
        return rx_s + self.base_s

    def _rank(self) -> float:
        return heapq.nlargest(min(CLOCK_RANK, len(self._samples)), (o for _, o in self._samples))[-1]
