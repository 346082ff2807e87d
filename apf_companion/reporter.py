"""The status reporter: STATUSTEXT on state changes, HEARTBEAT, NAMED_VALUE_FLOAT, the zenoh status, counters.

It owns the loop-latency window and the STATUSTEXT reason, and reads (never writes) the navigator, the perception
front end, the autopilot handlers and the edge counters (``ServiceCounters``: one record, incremented where input
is classified) to report them. ``due(now_s)`` sends whatever is due and returns when to call it next.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from apf_companion.errors import LinkError
from apf_companion.heap import GcPauses
from apf_companion.links import SigningStats
from apf_companion.navigator import CycleOutput, Navigator, State, StateChange
from apf_companion.outbox import Outbox
from apf_companion.perception import PerceptionFrontEnd
from apf_companion.status import (
    NVF_GOAL_DISTANCE,
    NVF_NEAREST_OBSTACLE,
    NVI_ERRORS,
    NVI_REJECTED_LINK,
    NVI_REJECTED_POSES,
    NVI_REJECTED_SCANS,
    NVI_REJECTED_SIGNING,
    encode_status_json,
    severity_for,
    statustext_for,
    system_status_for,
)

__all__ = [
    "AutopilotView",
    "Every",
    "FaultLog",
    "LatencyHistogram",
    "LatencyWindow",
    "ReporterParams",
    "ServiceCounters",
    "StatusRecord",
    "StatusReporter",
]

log = logging.getLogger(__name__)

LATENCY_WINDOW = 4096  # samples kept for the p50/p99 of the loop latency
# The whole run's latency goes into log-spaced bins, not a list: a list kept ~32 B per setpoint for ever (about 2 MB
# in the 30-minute soak of issue 9); the bins take 6 KB whatever the run's length and give p50/p99 within 1.2 %.
LATENCY_BINS_PER_DECADE = 100
LATENCY_MIN_MS = 1e-3  # lower edge of the first bin; smaller values share the underflow bin [ms]
LATENCY_DECADES = 8  # 1 us .. 100 s; larger values share the overflow bin
HEARTBEAT_PERIOD_S = 1.0


@dataclass(slots=True)
class ServiceCounters:
    """Counted at the service's edges (bad input is counted, never fatal); perception counts its own."""

    foreign_messages: int = 0  # not from the autopilot and not a command for us from a GCS
    undecodable_messages: int = 0  # a consumed message type whose fields could not be read
    goals: int = 0
    bad_goals: int = 0
    commands_for_us: int = 0
    param_requests: int = 0  # PARAM_* from a ground station addressed to us
    # Accepted PARAM_SETs without a planner build of their own: put into service together with others accepted in
    # the same cycle (one build before the next cycle, apf_companion.params), or setting the value already in force.
    param_sets_coalesced: int = 0
    mode_requests: int = 0
    handler_errors: int = 0  # an exception escaped a handler / cycle / report: caught, the task goes on
    rejected_ranges: int = 0  # range messages from neither the autopilot nor a [sensors] mavlink_sources id
    proximity_echoes_ignored: int = 0  # forwarding: the autopilot's DISTANCE_SENSOR echo of our own sectors
    forward_skipped: int = 0  # forwarding: no OBSTACLE_DISTANCE sent (no fresh pose or heading)
    slow_streams: int = 0  # streams asked for again because a message arrived too slowly (``streams.slow``)


class FaultLog:
    """Exceptions caught at a task's top (the task survives): counted in ``handler_errors``, logged once per
    (task, exception type) so a flood of hostile frames cannot flood the log."""

    def __init__(self, counters: ServiceCounters) -> None:
        self.counters = counters
        self.kinds: dict[str, int] = {}

    def caught(self, task: str, err: Exception) -> None:
        self.counters.handler_errors += 1
        kind = f"{task}:{type(err).__name__}"
        n = self.kinds.get(kind, 0)
        self.kinds[kind] = n + 1
        if n == 0:
            log.error("task.exception", extra={"task": task, "error": f"{type(err).__name__}: {err}"}, exc_info=err)


@dataclass(frozen=True, slots=True, kw_only=True)
class ReporterParams:
    statustext: bool = True
    named_value_rate_hz: float = 2.0
    zenoh_status_key: str = "apf/status"
    zenoh_status_rate_hz: float = 5.0
    dry_run: bool = False


class AutopilotView(Protocol):
    """What the reporter reads of the autopilot (apf_companion.handlers.AutopilotHandlers answers it; its part
    apf_companion.handling.vehicle.AutopilotState owns it)."""

    @property
    def armed(self) -> bool: ...


class LatencyHistogram:
    """Latency samples of a whole run in log-spaced bins: percentiles within half a bin, in constant memory [ms]."""

    def __init__(self) -> None:
        self.counts = np.zeros(LATENCY_DECADES * LATENCY_BINS_PER_DECADE + 2, dtype=np.int64)  # + under/overflow
        self.n = 0
        self._lo_ms = math.inf
        self._hi_ms = -math.inf

    def add(self, ms: float) -> None:
        if math.isnan(ms):
            return
        self.n += 1
        self._lo_ms, self._hi_ms = min(self._lo_ms, ms), max(self._hi_ms, ms)
        last = len(self.counts) - 1
        if ms < LATENCY_MIN_MS:
            i = 0
        elif ms >= LATENCY_MIN_MS * 10.0**LATENCY_DECADES:  # also inf, whose log cannot be a bin index
            i = last
        else:
            i = min(last, 1 + int(math.log10(ms / LATENCY_MIN_MS) * LATENCY_BINS_PER_DECADE))
        self.counts[i] += 1

    def percentile(self, q: float) -> float | None:
        """The ``q``-th percentile (nearest rank): its bin's geometric centre kept within the samples' range, or
        the smallest / largest sample when it falls in the under- / overflow bin."""
        if self.n == 0:
            return None
        rank = max(1, math.ceil(q / 100.0 * self.n))
        i = int(np.searchsorted(np.cumsum(self.counts), rank))
        if i == 0:
            return self._lo_ms
        if i == len(self.counts) - 1:
            return self._hi_ms
        centre = LATENCY_MIN_MS * math.pow(10.0, (i - 0.5) / LATENCY_BINS_PER_DECADE)
        return min(max(centre, self._lo_ms), self._hi_ms)


class LatencyWindow:
    """Sensor-to-setpoint latency: a sliding window for the status, and the whole run (binned) for the result [ms]."""

    def __init__(self) -> None:
        self._buf: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self.run = LatencyHistogram()

    def add(self, ms: float) -> None:
        self._buf.append(ms)
        self.run.add(ms)

    def summary(self) -> dict[str, float] | None:
        if not self._buf:
            return None
        arr = np.fromiter(self._buf, dtype=np.float64)
        p50, p99 = np.percentile(arr, [50.0, 99.0])
        return {"p50": float(p50), "p99": float(p99), "last": float(arr[-1])}

    def run_percentiles(self) -> tuple[float | None, float | None]:
        return self.run.percentile(50.0), self.run.percentile(99.0)


class Every:
    """One periodic send's schedule: due at once, then ``period_s`` after each time it went out (inf: never again)."""

    def __init__(self, period_s: float, now_s: float) -> None:
        self.period_s = period_s
        self.next_s = now_s

    def fire(self, now_s: float) -> bool:
        """Due at ``now_s``: True, and the next one is ``period_s`` later."""
        if now_s < self.next_s:
            return False
        self.next_s = now_s + self.period_s
        return True


class StatusRecord:
    """The status record and the counter totals, read (never written) from the service's parts."""

    def __init__(
        self,
        *,
        outbox: Outbox,
        navigator: Navigator,
        perception: PerceptionFrontEnd,
        autopilot: AutopilotView,
        counters: ServiceCounters,
        signing: SigningStats | None,
    ) -> None:
        self.outbox = outbox
        self.navigator = navigator
        self.perception = perception
        self.autopilot = autopilot
        self.counters = counters
        self.signing = signing  # the autopilot link's signature verdicts (None: signing off)

    def rejected(self) -> dict[str, int]:
        """The rejected-input totals sent as NAMED_VALUE_INT (docs/hardening.md): poses, scans / memory clears,
        link input (foreign, undecodable, bad goals), frames refused by the signing check and errors caught or values
        not sendable."""
        c, p, o = self.counters, self.perception.counters, self.outbox
        pose = p.bad_poses + p.stale_poses + p.out_of_bounds_poses + p.implausible_poses + p.pose_time_jumps
        pose += p.pose_time_leads + p.pose_conflicts + p.stale_attitudes + p.bad_attitude_rates
        return {
            NVI_REJECTED_POSES: pose,
            NVI_REJECTED_SCANS: p.bad_scans + p.clears_refused,
            NVI_REJECTED_LINK: c.foreign_messages + c.undecodable_messages + c.bad_goals + c.rejected_ranges,
            NVI_REJECTED_SIGNING: 0 if self.signing is None else self.signing.rejected,
            NVI_ERRORS: c.handler_errors + o.send_errors + o.unsendable,
        }

    def counts(self) -> dict[str, int]:
        """Every edge counter: the service's, perception's, the setpoints / STATUSTEXTs sent and (``signing_``
        prefixed) the signature verdicts."""
        sent = self.outbox.counts()
        out = dataclasses.asdict(self.counters) | dataclasses.asdict(self.perception.counters) | sent
        if self.signing is not None:
            out |= {f"signing_{k}": v for k, v in dataclasses.asdict(self.signing).items()}
        return out

    def status_dict(
        self,
        now_s: float,
        *,
        reason: str,
        loop_latency_ms: dict[str, float] | None,
        gc: dict[str, Any] | None,
        fence: dict[str, object] | None,
    ) -> dict[str, Any]:
        """The status record (see apf_companion.status for the schema) with what the reporter keeps: the latest
        state change's ``reason``, the loop latency, the collector's pauses and the fence reader's summary."""
        nav = self.navigator
        out = nav.last_output
        return {
            "t_s": now_s,
            "state": nav.state.value,
            "reason": reason,
            "pose": self._pose_dict(now_s),
            "goal": self._goal_dict(),
            "distance_to_goal_m": None if out is None else out.distance_to_goal_m,
            "nearest_obstacle_m": None if out is None else out.nearest_obstacle_m,
            "n_obstacles": len(self.perception),
            "sensor_look_deg": math.degrees(self.perception.look_offset_rad(now_s)),
            "loop_latency_ms": loop_latency_ms,
            "gc": gc,
            "fence": fence,
            "decision": None if out is None else out.decision,
            "autopilot": {"mode_ok": nav.mode_ok, "armed": self.autopilot.armed, "link_alive": nav.link_alive(now_s)},
            "counters": self.counts() | {f"nav_{k}": v for k, v in nav.counts().items()},
            "rejected": self.rejected(),
        }

    def _pose_dict(self, now_s: float) -> dict[str, float] | None:
        pose = self.navigator.pose
        if pose is None:
            return None
        p = pose.pos_ned_m
        yaw_deg = math.degrees(pose.yaw_rad)
        return {
            "north_m": float(p[0]),
            "east_m": float(p[1]),
            "down_m": float(p[2]),
            "yaw_deg": yaw_deg,
            "age_s": now_s - pose.t_s,
        }

    def _goal_dict(self) -> dict[str, Any] | None:
        """The goal taken (flown, or held for its check: ``held``): the waypoint being flown to, or before its first
        leg starts (no pose yet, waiting for the pilot or the takeover) the route's first waypoint, ``leg`` null and
        a "keep the altitude" ``down_m`` null (JSON has no NaN)."""
        nav = self.navigator
        route = nav.goal.taken
        if route is None:
            return None
        target = nav.active_target_ned_m if nav.route is not None else None
        leg = nav.leg_index if target is not None else None
        point = route.waypoints_ned_m[0] if target is None else target
        north, east, down = (float(v) for v in point)
        return {
            "north_m": north,
            "east_m": east,
            "down_m": down if math.isfinite(down) else None,
            "leg": leg,
            "legs": len(route),
            "source": route.source,
            "held": nav.held is not None,
        }


class StatusReporter:
    """Reports the service's state to the autopilot / ground station (MAVLink) and to zenoh.

    It owns the STATUSTEXT reason, the periodic sends' schedules (``Every``), the loop-latency window and what the
    service attaches while it runs (the collector's pauses, the fence reader's summary); the status record and the
    counter totals are read by its ``record`` (``StatusRecord``).
    """

    def __init__(
        self,
        params: ReporterParams,
        *,
        outbox: Outbox,
        navigator: Navigator,
        perception: PerceptionFrontEnd,
        autopilot: AutopilotView,
        counters: ServiceCounters,
        zenoh: Any,
        now_s: float,
        signing: SigningStats | None = None,
    ) -> None:
        self.params = params
        self.outbox = outbox
        self.navigator = navigator
        self.zenoh = zenoh
        self.counters = counters
        self.record = StatusRecord(
            outbox=outbox,
            navigator=navigator,
            perception=perception,
            autopilot=autopilot,
            counters=counters,
            signing=signing,
        )
        self.latency = LatencyWindow()
        self.gc: GcPauses | None = None  # the collector's pauses while the service runs (``CompanionService.run``)
        #: The fence reader's summary (``FenceReader.summary``), when the service reads the autopilot's fence.
        self.fence: Callable[[], dict[str, object]] | None = None
        self.reason = "starting"
        nvf_hz = params.named_value_rate_hz
        self._heartbeat = Every(HEARTBEAT_PERIOD_S, now_s)
        self._named_values = Every(1.0 / nvf_hz if nvf_hz > 0 else math.inf, now_s)
        self._zenoh_status = Every(1.0 / params.zenoh_status_rate_hz, now_s)

    def changes(self, changes: list[StateChange]) -> None:
        """Log each state change and announce it in a STATUSTEXT (except LINK_LOST: silence towards the autopilot)."""
        for ch in changes:
            self.reason = ch.reason
            log.info(
                "state.change", extra={"old": ch.old.value, "new": ch.new.value, "reason": ch.reason, "t_s": ch.t_s}
            )
            if ch.new is not State.LINK_LOST:
                self.statustext(severity_for(ch.new), statustext_for(ch.new, ch.reason))

    def statustext(self, severity: int, text: str) -> None:
        if self.params.statustext and not self.outbox.silent:
            self.outbox.statustext(severity, text)

    def due(self, now_s: float) -> float:
        """Send the HEARTBEAT (1 Hz), NAMED_VALUE_FLOATs and zenoh status that are due; the next due time."""
        if self._heartbeat.fire(now_s):
            self.outbox.heartbeat(system_status_for(self.navigator.state, healthy_inputs=self._inputs_healthy(now_s)))
        if self._named_values.fire(now_s):
            self._send_named_values()
        if self.zenoh is not None and self._zenoh_status.fire(now_s):
            self._publish_status(now_s)
        zenoh_next_s = self._zenoh_status.next_s if self.zenoh is not None else math.inf
        return min(self._heartbeat.next_s, self._named_values.next_s, zenoh_next_s)

    def _inputs_healthy(self, now_s: float) -> bool:
        return self.navigator.pose_fresh(now_s) and self.navigator.ranges_fresh(now_s)

    def _send_named_values(self) -> None:
        out = self.navigator.last_output
        if out is None or self.navigator.state is State.LINK_LOST or self.outbox.silent:
            return
        for name, value in (
            (NVF_GOAL_DISTANCE, out.distance_to_goal_m),
            (NVF_NEAREST_OBSTACLE, out.nearest_obstacle_m),
        ):
            if value is not None and math.isfinite(value):
                self.outbox.named_value_float(name, value)
        for name, count in self.rejected().items():
            self.outbox.named_value_int(name, count)

    def _publish_status(self, now_s: float) -> None:
        if self.zenoh is None or self.params.dry_run:
            return
        try:
            self.zenoh.publish(self.params.zenoh_status_key, encode_status_json(self.status_dict(now_s)))
        except LinkError:
            log.debug("status.publish_failed", exc_info=True)

    def rejected(self) -> dict[str, int]:
        """The rejected-input totals (``StatusRecord.rejected``)."""
        return self.record.rejected()

    def counts(self) -> dict[str, int]:
        """Every edge counter (``StatusRecord.counts``)."""
        return self.record.counts()

    def status_dict(self, now_s: float) -> dict[str, Any]:
        """The status record (``StatusRecord.status_dict``)."""
        return self.record.status_dict(
            now_s,
            reason=self.reason,
            loop_latency_ms=self.latency.summary(),
            gc=self.gc_summary(),
            fence=None if self.fence is None else self.fence(),
        )

    def gc_summary(self) -> dict[str, Any] | None:
        """The collector's pauses since the run started (``heap.GcSummary``), None before."""
        return None if self.gc is None else self.gc.summary().to_dict()

    def cycle_sent(self, out: CycleOutput, trigger_wall_s: float | None, now_wall_s: float) -> None:
        """A cycle's setpoint went out: its latency from the pose that triggered it (if one did)."""
        if out.setpoint is not None and trigger_wall_s is not None:
            self.latency.add((now_wall_s - trigger_wall_s) * 1000.0)
