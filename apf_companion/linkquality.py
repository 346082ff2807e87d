"""Link quality and caution: fewer setpoints arriving means shorter, slower steps (docs/hardening.md).

On a lossy link any setpoint may be the last one the autopilot receives for a while, and the pose the service
plans from may be older than it looks. The navigator therefore scales each step by ``caution_scale``, a pure
function of what the service measures about the link:

- pose loss: the share of the autopilot's LOCAL_POSITION_NED stream that did not arrive (or arrived out of
  order and was refused), from the gaps in its own ``time_boot_ms`` over the last ``window_s``;
- pose age: how old the newest pose is when the cycle runs (a pose-triggered cycle sees ~0; a timer cycle after
  lost poses sees more);
- send failures: the share of setpoint sends that failed locally over the last ``window_s``.

The link is assumed symmetric: poses lost on the way in mean setpoints are lost on the way out.
Pure and clock-injected: every input carries its time stamp; nothing reads a clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from apf_companion.errors import ConfigError

INTERVAL_MEMORY_WINDOWS = 10  # the smallest gap is looked for over this many windows
SINGLE_GAP = 1.5  # a gap up to this many smallest gaps is one interval (stamp jitter < half an interval)
INTERVAL_GAIN = 0.1  # the interval estimate's step towards each new single-interval gap
_STAMP_EPS_S = 1e-6  # stamps are whole milliseconds: a pose exactly one window back is still in it

__all__ = ["CLEAN_LINK", "CautionParams", "LinkMeter", "LinkQuality", "caution_scale"]


@dataclass(frozen=True, slots=True, kw_only=True)
class CautionParams:
    """How link quality turns into caution (``[safety] caution_*``).

    Attributes:
        min_scale: The smallest step and speed fraction, reached at ``full_loss`` or ``full_age_s``; 1 = off.
        full_loss: Pose loss (or send failure) share at which the scale reaches ``min_scale`` (linear from 0).
        ok_age_s: A pose up to this old at the cycle costs nothing [s].
        full_age_s: A pose this old gives ``min_scale`` (the navigator holds beyond ``pose_max_age_s``) [s].
        window_s: Loss and send failures are measured over this long [s].
    """

    min_scale: float = 0.5
    full_loss: float = 0.5
    ok_age_s: float = 0.2
    full_age_s: float = 0.5
    window_s: float = 2.0

    def __post_init__(self) -> None:
        if not 0.0 < self.min_scale <= 1.0:
            msg = f"caution min_scale must be in (0, 1], got {self.min_scale}"
            raise ConfigError(msg)
        if not 0.0 < self.full_loss <= 1.0:
            msg = f"caution full_loss must be in (0, 1], got {self.full_loss}"
            raise ConfigError(msg)
        if not 0.0 <= self.ok_age_s < self.full_age_s:
            msg = f"caution ages must satisfy 0 <= ok_age_s < full_age_s, got {self.ok_age_s}, {self.full_age_s}"
            raise ConfigError(msg)
        if not self.window_s > 0.0:
            msg = f"caution window_s must be > 0, got {self.window_s}"
            raise ConfigError(msg)


@dataclass(frozen=True, slots=True, kw_only=True)
class LinkQuality:
    """What the service measured about the autopilot link at one cycle.

    Attributes:
        pose_loss: Share of the autopilot's poses that did not arrive over the window, in [0, 1].
        pose_age_s: Age of the newest accepted pose at the cycle (service clock) [s].
        send_failures: Share of setpoint sends that failed over the window, in [0, 1].
    """

    pose_loss: float = 0.0
    pose_age_s: float = 0.0
    send_failures: float = 0.0


CLEAN_LINK = LinkQuality()
"""Nothing lost, a fresh pose: no caution (``Navigator.cycle``'s default)."""


def _ramp(x: float, lo: float, hi: float) -> float:
    """0 at ``lo`` or below, 1 at ``hi`` or above, linear between; NaN counts as the worst."""
    if not x <= hi:  # also NaN
        return 1.0
    return max(0.0, (x - lo) / (hi - lo))


def caution_scale(q: LinkQuality, p: CautionParams) -> float:
    """The fraction of a full step (and of the feed-forward speed and silent drift) to fly, in [min_scale, 1].

    1 on a clean link; falls linearly with the worst of loss / send failures (to ``min_scale`` at ``full_loss``)
    and with the pose age beyond ``ok_age_s`` (to ``min_scale`` at ``full_age_s``).
    """
    worst = max(
        _ramp(q.pose_loss, 0.0, p.full_loss),
        _ramp(q.send_failures, 0.0, p.full_loss),
        _ramp(q.pose_age_s, p.ok_age_s, p.full_age_s),
    )
    return 1.0 - (1.0 - p.min_scale) * worst


class LinkMeter:
    """Measures pose loss and send failures from stamped events (fed by the service, read by the navigator).

    Pose loss: the autopilot streams LOCAL_POSITION_NED at a fixed interval of its own clock, so a gap of ``k``
    intervals between consecutive accepted ``time_boot_ms`` means ``k - 1`` poses were lost. The interval is
    learnt from the single-interval gaps: those within ``SINGLE_GAP`` times the smallest gap of the last
    ``INTERVAL_MEMORY_WINDOWS`` windows (stamps jitter by a loop or a physics step, so the smallest gap alone
    is too short), averaged. Only accepted poses are fed (a duplicate or a reordered, older pose is refused by
    the pose gate and counts as lost). A stream that lost every other pose since that memory began reads as a
    stream at half the rate.
    """

    def __init__(self, params: CautionParams) -> None:
        self.p = params
        self._last_s: float | None = None  # newest accepted stamp
        self._window: deque[tuple[float, float]] = deque()  # (stamp, gap before it) of the poses in the window
        self._min: deque[tuple[float, float]] = deque()  # (stamp, gap), increasing gaps: a sliding minimum
        self._interval_s: float | None = None  # the stream's interval (mean of the single-interval gaps)
        self._sends: deque[tuple[float, bool]] = deque()  # (service time, sent) of setpoint sends

    def pose(self, time_boot_ms: int) -> None:
        """An accepted pose with the autopilot's stamp ``time_boot_ms``."""
        t_s = time_boot_ms / 1000.0
        last, self._last_s = self._last_s, t_s
        if last is None or t_s <= last:  # the first pose, or a new time base (reboot, re-anchor): start over
            self._window.clear()
            self._min.clear()
            self._interval_s = None
            return
        gap = t_s - last
        self._window.append((t_s, gap))
        while t_s - self._window[0][0] > self.p.window_s + _STAMP_EPS_S:
            self._window.popleft()
        while self._min and self._min[-1][1] >= gap:
            self._min.pop()
        self._min.append((t_s, gap))
        while t_s - self._min[0][0] > INTERVAL_MEMORY_WINDOWS * self.p.window_s:
            self._min.popleft()
        if gap <= SINGLE_GAP * self._min[0][1]:
            old = self._interval_s
            self._interval_s = gap if old is None else old + INTERVAL_GAIN * (gap - old)

    def sent(self, ok: bool, now_s: float) -> None:
        """A setpoint send at ``now_s``: ``ok`` False when it failed locally (socket error, unsendable)."""
        self._sends.append((now_s, ok))
        self._trim_sends(now_s)

    def _trim_sends(self, now_s: float) -> None:
        while self._sends and now_s - self._sends[0][0] > self.p.window_s:
            self._sends.popleft()

    def pose_loss(self) -> float:
        """Share of the poses the window should hold that did not arrive (0 until the interval is known)."""
        interval_s = self._interval_s
        if interval_s is None or not self._window:
            return 0.0
        lost = sum(max(0, round(gap / interval_s) - 1) for _, gap in self._window)
        return lost / (lost + len(self._window))

    def quality(self, now_s: float, pose_t_s: float | None) -> LinkQuality:
        """The link as measured at ``now_s``; ``pose_t_s`` is the receive time of the pose planned from."""
        self._trim_sends(now_s)
        failed = sum(not ok for _, ok in self._sends)
        age = 0.0 if pose_t_s is None else max(0.0, now_s - pose_t_s)
        return LinkQuality(
            pose_loss=self.pose_loss(),
            pose_age_s=age,
            send_failures=failed / len(self._sends) if self._sends else 0.0,
        )
