"""The companion service: MAVLink (and zenoh) in, planner cycle, setpoints and status out.

``CompanionService`` only wires parts that each own their state (docs/architecture-service.md):

- ``PerceptionFrontEnd`` (apf_companion.perception): pose history, scan timing and deferral, the obstacle memory.
- ``Navigator`` (apf_companion.navigator): states, freshness, the planner, setpoints; pure, clock injected.
- ``GoalAdmission`` (apf_companion.goaladmission): every goal checked against the limits, then flown, held for
  its check (until the first pose) or refused.
- ``TakeoverController`` (apf_companion.takeover): GUIDED / OFFBOARD, arm, takeoff, pre-stream; pure.
- ``AutopilotHandlers`` (apf_companion.handlers): decoded MAVLink records to the part that owns them.
- ``StatusReporter`` (apf_companion.reporter) and ``Outbox`` (apf_companion.outbox): everything sent.

MAVLink messages are decoded once into typed records (apf_companion.links.messages) as they arrive. One
``asyncio.TaskGroup`` runs the named tasks: ``apf.rx`` (the autopilot link), ``apf.cycle`` (a planning cycle when a
new pose arrives, at most ``rate_hz``, and on a timer one period after the last cycle otherwise, so a frozen pose
is noticed within one cycle), ``apf.status`` (HEARTBEAT at 1 Hz, NAMED_VALUE_FLOAT and the zenoh status at their
rates), ``apf.takeover`` (steps the takeover controller), ``apf.params`` (the paced PARAM_VALUE list of
apf_companion.params), ``apf.forward`` (OBSTACLE_DISTANCE to the autopilot, when ``[sensors]
forward_obstacle_distance``), ``apf.zenoh`` (scans and goals from zenoh, when enabled) and ``apf.fence`` (the
autopilot's fence as bapf-nav's flying area, read at start and every ``planner.fence_poll_s``,
apf_companion.fencereader; when ``planner.fence_area`` and the config gives no area).

Clock: ``ServiceClock`` is monotonic and scaled by ``cycle.time_scale`` (vehicle seconds per wall second), so a
simulated vehicle running N times faster than real time keeps every limit's meaning in vehicle seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from apf_companion.builders import (
    admission_params,
    build_navigator,
    build_outbox,
    build_planner,
    config_with_fence,
    fence_not_read,
    flying_area,
    forwarder_params,
    handler_params,
    has_zones,
    initial_route,
    keepout_zones,
    navigator_params,
    perception_params,
    reporter_params,
    signing_setup,
    takeover_params,
)
from apf_companion.config import ServiceConfig, ZenohSection
from apf_companion.errors import ApfCompanionError, ConfigError, ProtocolError
from apf_companion.fence import FenceArea, FenceOutcome
from apf_companion.fencereader import STEP_S, FenceReader, FenceReaderParams
from apf_companion.flightend import FlightEnd, Outcome
from apf_companion.forwarder import ObstacleForwarder
from apf_companion.goal import GlobalReference, Route
from apf_companion.goaladmission import GoalAdmission, GoalBounds
from apf_companion.handlers import AutopilotHandlers
from apf_companion.heap import GcPauses
from apf_companion.linkquality import LinkMeter
from apf_companion.links import MavlinkLink, TimestampKeeper
from apf_companion.links.endpoint import connection_hint, parse_endpoint
from apf_companion.links.messages import DECODERS, Source, decode, source
from apf_companion.navigator import CycleOutput, Navigator, State, reconfigure
from apf_companion.observe import CycleObserver, Observers
from apf_companion.outbox import Outbox
from apf_companion.params import ParamServer
from apf_companion.perception import PerceptionFrontEnd, decode_goal_json
from apf_companion.planning import BapfNavPlanner
from apf_companion.reporter import FaultLog, ServiceCounters, StatusReporter
from apf_companion.sdnotify import SystemdNotifier, Watchdog
from apf_companion.setpoint import Setpoint, SetpointKind
from apf_companion.takeover import Action, ActionKind, TakeoverController, TakeoverInputs

__all__ = [
    "CompanionService",
    "Outcome",
    "ServiceClock",
    "ServiceResult",
    "build_navigator",
    "build_planner",
    "initial_route",
]

log = logging.getLogger(__name__)

MIN_GAP_FRACTION = 0.8  # jitter margin: a pose stream at the cycle rate triggers every cycle
TIMER_PERIODS = 1.25  # a timer cycle when no pose triggered one for this many periods
NO_HEARTBEAT_WARN_S = 5.0  # no autopilot HEARTBEAT this long after start: a WARNING saying what to check [s]
NO_HEARTBEAT_REPEAT_S = 60.0  # ... repeated this often while still nothing is heard [s]
LINK_LOST_REPEAT_S = 15.0  # while LINK_LOST: a WARNING this often saying for how long [s]
DRY_RUN_NO_POSE_WARN_S = 5.0  # dry run, autopilot heard, no LOCAL_POSITION_NED this long after start: one WARNING [s]
DRY_RUN_NO_POSE_AFTER_HEARD_S = 2.0  # ... and at least this long after its first HEARTBEAT [s]
# ArduPilot's stream groups (GCS_MAVLink, STREAM_POSITION_msgs: LOCAL_POSITION_NED; STREAM_EXTRA1_msgs: ATTITUDE);
# PX4 streams per MAVLink instance mode (MAV_n_MODE) or the `mavlink stream` shell command.
DRY_RUN_NO_POSE_HINT = (
    "dry run sends no stream requests (SET_MESSAGE_INTERVAL): have the autopilot stream LOCAL_POSITION_NED and "
    "ATTITUDE itself (ArduPilot SRn_POSITION and SRn_EXTRA1 for the port's MAVLink channel n, e.g. SR1_POSITION = "
    "10; PX4 MAV_n_MODE Onboard, or `mavlink stream -d <port> -s LOCAL_POSITION_NED -r 20`), or run a ground "
    "station that asks for them"
)


class ServiceClock:
    """Monotonic service time in vehicle seconds: wall seconds since creation times ``time_scale``."""

    def __init__(self, time_scale: float = 1.0) -> None:
        self.time_scale = time_scale
        self._t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.time_scale

    def to_wall(self, dt_s: float) -> float:
        """A duration in vehicle seconds as wall seconds."""
        return max(0.0, dt_s) / self.time_scale

    async def sleep(self, dt_s: float) -> None:
        await asyncio.sleep(self.to_wall(dt_s))


@dataclass(frozen=True, slots=True, kw_only=True)
class ServiceResult:
    """How a run ended (``apf-companion run --result-json``).

    Attributes:
        outcome: "arrived", "stuck", "timeout", "link_lost", "stopped" or "error".
        state: The navigator state at the end.
        steps: Planner steps taken.
        flight_time_s: Vehicle seconds of the last flight: from its first navigation setpoint to the state that
            ended it (arrived, stuck, timeout, link lost, goal dropped), or to the end of the run if it was
            stopped before one; 0 if it never navigated. A goal replacing one still being flown continues the
            flight (``apf_companion.flightend.FlightEnd``).
        latency_ms_p50, latency_ms_p99: Sensor-to-setpoint latency over the run [ms].
        gc: The garbage collector's pauses over the run (``heap.GcSummary``), None if it did not run.
        counters: Service and navigator counters.
        error: Message of the error that ended the run, if any.
    """

    outcome: str
    state: str
    steps: int
    flight_time_s: float
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    gc: dict[str, Any] | None = None
    counters: dict[str, int] = field(default_factory=dict)
    error: str | None = None

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, allow_nan=False)

    @classmethod
    def unopened(cls, outcome: str, *, error: str | None) -> ServiceResult:
        """The result of a run that ended while the service was opening its links (nothing flown or counted)."""
        idle = State.IDLE.value
        return cls(
            outcome=outcome,
            state=idle,
            steps=0,
            flight_time_s=0.0,
            latency_ms_p50=None,
            latency_ms_p99=None,
            error=error,
        )

    @classmethod
    def of(
        cls,
        outcome: str,
        navigator: Navigator,
        reporter: StatusReporter,
        link: MavlinkLink | None,
        *,
        flight_s: float,
        error: str | None,
    ) -> ServiceResult:
        """The result from the parts' counters (status, navigator, link) at the end of a run."""
        p50, p99 = reporter.latency.run_percentiles()
        counters = reporter.counts() | {f"nav_{k}": v for k, v in navigator.counts().items()}
        if link is not None:
            counters |= {f"link_{k}": v for k, v in dataclasses.asdict(link.stats).items()}
        return cls(
            outcome=outcome,
            state=navigator.state.value,
            steps=navigator.counters.planner_steps,
            flight_time_s=flight_s,
            latency_ms_p50=p50,
            latency_ms_p99=p99,
            gc=reporter.gc_summary(),
            counters=counters,
            error=error,
        )


class CycleTrigger:
    """When the planning cycle runs: on each new pose, at most one per ``MIN_GAP_FRACTION`` of a period, and on a
    timer when no pose triggered one for ``TIMER_PERIODS`` periods (a frozen or lost pose is still noticed within
    one period of its limit)."""

    def __init__(self, clock: ServiceClock, rate_hz: float) -> None:
        self.clock = clock
        self.period_s = 1.0 / rate_hz
        self._new_pose = asyncio.Event()
        self._rx_wall: float | None = None  # wall time the triggering pose was read

    @property
    def pending(self) -> bool:
        return self._new_pose.is_set()

    def pose_arrived(self, rx_wall: float) -> None:
        self._rx_wall = rx_wall
        self._new_pose.set()

    async def cycles(self) -> AsyncIterator[tuple[float, float | None]]:
        """(service time, wall time the triggering pose was read or None for a timer cycle), forever."""
        min_gap = MIN_GAP_FRACTION * self.period_s
        last_cycle = self.clock.now()
        last_triggered = -math.inf
        while True:
            timeout = self.clock.to_wall(last_cycle + TIMER_PERIODS * self.period_s - self.clock.now())
            triggered = False
            if timeout > 0:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(timeout):
                        await self._new_pose.wait()
                        triggered = True
            now = self.clock.now()
            trigger, self._rx_wall = self._rx_wall, None
            self._new_pose.clear()
            if triggered:
                if now - last_triggered < min_gap:
                    continue  # a faster pose stream than the cycle rate: skip this one
                last_triggered = now
            else:
                trigger = None
            last_cycle = now
            yield now, trigger


class CompanionService:
    """The running service. Create with ``await CompanionService.open(config)``, then ``await run()``.

    Args:
        config: Validated configuration.
        route: Goal to fly once the autopilot is heard (overrides ``[goal]``); None = the config's goal.
        clock: Service clock (tests may pass one); default ``ServiceClock(config.cycle.time_scale)``.
        result_path: Where ``run`` writes the ``ServiceResult`` JSON when it ends.
        link: The open autopilot link (``open`` passes it), or None (nothing is sent or received).
        zenoh: The open zenoh link (``open`` passes it when enabled), or None.
        observers: Read-only watchers of each cycle; None = those ``[visualisation]`` asks for (Foxglove).
        signing_keeper: Saves the link's signing timestamp (``open`` passes it when signing is configured).
        notifier: systemd notifications (``open`` passes ``SystemdNotifier.from_env()``): READY=1 once running,
            WATCHDOG=1 and STATUS= from completed planning cycles, STOPPING=1 at the end; None = none.
    """

    def __init__(
        self,
        config: ServiceConfig,
        *,
        route: Route | None = None,
        clock: ServiceClock | None = None,
        result_path: Path | None = None,
        link: MavlinkLink | None = None,
        zenoh: Any = None,
        observers: Sequence[CycleObserver] | None = None,
        signing_keeper: TimestampKeeper | None = None,
        notifier: SystemdNotifier | None = None,
    ) -> None:
        self.config = config
        self.signing_keeper = signing_keeper
        self.clock = clock or ServiceClock(config.cycle.time_scale)
        self.result_path = result_path
        self.link = link
        self.zenoh = zenoh
        self.planner = build_planner(config)
        self.perception = PerceptionFrontEnd(perception_params(config))
        self.counters = ServiceCounters()
        self.faults = FaultLog(self.counters)
        self.observers = Observers(self.faults)
        self.navigator = build_navigator(config, self.observers.tap(self.planner), self.perception)
        self.flight = FlightEnd(self.clock.now())
        self.admission = _goal_admission(self, route if route is not None else initial_route(config, self.planner))
        self.link_meter = LinkMeter(self.navigator.params.caution)  # pose loss and send failures: caution
        self.outbox = build_outbox(config, link, self.clock.now)
        self.handlers = self._autopilot_handlers(config)
        self.reporter = StatusReporter(
            reporter_params(config),
            outbox=self.outbox,
            navigator=self.navigator,
            perception=self.perception,
            autopilot=self.handlers,
            counters=self.counters,
            zenoh=zenoh,
            now_s=self.clock.now(),
            signing=None if link is None or link.signing is None else link.signing.stats,
        )
        self.forwarder, self.takeover = self._drivers(config)
        self.notifier, self.watchdog = notifier, (Watchdog(notifier) if notifier is not None else None)
        self.params = _param_server(self)
        self.fence = _fence_reader(self)  # bapf-nav without zones: the autopilot's fence as its area and keep-outs
        self.reporter.fence = None if self.fence is None else self.fence.summary
        self._stop = asyncio.Event()
        self.trigger = CycleTrigger(self.clock, config.cycle.rate_hz)
        self.observers.add(_open_observers(config, self.clock) if observers is None else observers)  # last: opens

    def _autopilot_handlers(self, config: ServiceConfig) -> AutopilotHandlers:
        """Decoded MAVLink records to the parts that own them (the late-bound ones exist by the first record)."""
        return AutopilotHandlers(
            handler_params(config),
            perception=self.perception,
            navigator=self.navigator,
            outbox=self.outbox,
            counters=self.counters,
            set_route=self.admission.admit,
            on_pose=self._pose_arrived,
            route_at_start=self.admission.start_route,
            on_param=lambda rec, now_s: self.params.handle(rec, now_s),
            on_fence=lambda rec: None if self.fence is None else self.fence.on_record(rec),
            statustext=self.statustext,
        )

    def statustext(self, severity: int, text: str) -> None:
        """A STATUSTEXT as the reporter sends them (for the parts built before it: handlers, goal admission)."""
        self.reporter.statustext(severity, text)

    def _drivers(self, config: ServiceConfig) -> tuple[ObstacleForwarder, TakeoverDriver]:
        """The parts that send on their own schedule: OBSTACLE_DISTANCE forwarding and the takeover."""
        forwarder = ObstacleForwarder(
            forwarder_params(config), perception=self.perception, navigator=self.navigator, outbox=self.outbox,
            counters=self.counters,
        )  # fmt: skip
        takeover = TakeoverDriver(
            TakeoverController(takeover_params(config)),
            navigator=self.navigator,
            handlers=self.handlers,
            outbox=self.outbox,
            reporter=self.reporter,
            profile=config.autopilot.profile,
        )
        return forwarder, takeover

    # ---- lifecycle ---------------------------------------------------------------------------------------------
    @classmethod
    async def open(
        cls,
        config: ServiceConfig,
        *,
        route: Route | None = None,
        clock: ServiceClock | None = None,
        result_path: Path | None = None,
    ) -> CompanionService:
        """Build the service and open its links (MAVLink, and zenoh when enabled).

        Raises:
            ConfigError: planner parameters or the route file are invalid.
            LinkError: a link cannot be opened.
        """
        planner = build_planner(config)  # config errors (planner, route file) before any socket is opened
        route = route if route is not None else initial_route(config, planner)
        link, keeper = await _open_mavlink(config)
        zenoh = None
        try:
            if config.zenoh.enabled:
                zenoh = await _open_zenoh(config)
            return cls(
                config,
                route=route,
                clock=clock,
                result_path=result_path,
                link=link,
                zenoh=zenoh,
                signing_keeper=keeper,
                notifier=SystemdNotifier.from_env(),
            )
        except BaseException:
            if zenoh is not None:
                await zenoh.aclose()
            await link.aclose()
            raise

    async def aclose(self) -> None:
        """Close the links, the observers and the systemd notification socket (safe to call twice)."""
        self.observers.close()
        if self.notifier is not None:
            self.notifier.close()
        if self.link is not None:
            await self.link.aclose()
        if self.signing_keeper is not None:
            self.signing_keeper.close()  # the last signing timestamp, after the last frame
        if self.zenoh is not None:
            zl, self.zenoh = self.zenoh, None
            self.reporter.zenoh = None
            await zl.aclose()

    def stop(self) -> None:
        """Ask ``run`` to end (it returns with outcome "stopped" unless the flight already ended)."""
        self._stop.set()

    async def run(self) -> ServiceResult:
        """Run until ``stop()``, or until the flight ends when ``exit_when_done``. Closes the links at the end."""
        error: str | None = None
        pauses = self.reporter.gc = GcPauses()
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._rx(), name="apf.rx"),
                    tg.create_task(self._cycle_loop(), name="apf.cycle"),
                    tg.create_task(self._periodic("status", _status_due(self), 1.0), name="apf.status"),
                    tg.create_task(self._takeover_loop(), name="apf.takeover"),
                    tg.create_task(self.params.run(), name="apf.params"),
                ]
                tasks += [tg.create_task(coro, name=name) for name, coro in _optional_tasks(self)]
                _sd_notify(self, READY=1, STATUS=_status_text(self))
                await self._stop.wait()
                for task in tasks:
                    task.cancel()
        except* ApfCompanionError as eg:
            error = "; ".join(str(e) for e in eg.exceptions)
            log.error("service.error", extra={"error": error})
            self.flight.outcome = Outcome.ERROR
        finally:
            _sd_notify(self, STOPPING=1, STATUS=f"stopping: {self.flight.outcome or Outcome.STOPPED}")
            pauses.close()  # its summary stays for the result
            await self.aclose()
        result = self.result(error=error or self.admission.error)
        if self.result_path is not None:
            self.result_path.write_text(result.to_json() + "\n", encoding="utf-8")
        return result

    def result(self, *, error: str | None = None) -> ServiceResult:
        outcome, flight = self.flight.final(self.clock.now())
        return ServiceResult.of(outcome, self.navigator, self.reporter, self.link, flight_s=flight, error=error)

    # ---- tasks -------------------------------------------------------------------------------------------------
    async def _rx(self) -> None:
        assert self.link is not None
        async for msg in self.link.messages():
            try:
                rec = decode(msg)
                if rec is None:
                    self.handlers.undecoded(msg.get_type() in DECODERS, source(msg))
                    continue
                self.handlers.handle(rec, self.clock.now())
            except Exception as err:
                # Bad input is counted where it is classified; anything that still escapes a handler is counted
                # and logged here, and the loop goes on (no value on the wire may end the service).
                self.faults.caught("rx", err)
            if self.trigger.pending:
                await asyncio.sleep(0)  # let the cycle run before more input is processed

    def _pose_arrived(self, time_boot_ms: int) -> None:
        self.link_meter.pose(time_boot_ms)
        self.trigger.pose_arrived(time.perf_counter())
        self.admission.pose_arrived(self.clock.now())  # a held goal's check needed a position

    async def _cycle_loop(self) -> None:
        async for now, trigger in self.trigger.cycles():
            try:
                self.run_cycle(now, trigger)
            except Exception as err:
                self.faults.caught("cycle", err)
                continue  # a failing cycle does not pet the systemd watchdog
            if self.watchdog is not None:
                self.watchdog.pet(_status_text(self))

    def run_cycle(self, now: float, trigger_wall: float | None = None) -> CycleOutput:
        """One navigator cycle at ``now``: send its setpoint, report its changes, end the run if it is done."""
        self.params.apply_pending()  # the PARAM_SETs accepted since the last cycle: one planner build for them all
        pose_t_s = None if self.navigator.pose is None else self.navigator.pose.t_s
        out = self.navigator.cycle(now, self.link_meter.quality(now, pose_t_s))
        sp = out.setpoint
        if sp is not None:
            if sp.kind is SetpointKind.PRESTREAM:
                self.takeover.controller.note_prestream(now)
            elif sp.kind is SetpointKind.NAVIGATE:
                self.flight.navigating(now)
            sent = self.outbox.setpoint(sp)
            if not self.outbox.silent:  # dry run: nothing is sent, nothing failed
                self.link_meter.sent(sent, now)
            self.reporter.cycle_sent(out, trigger_wall, time.perf_counter())
            _log_setpoint(out, sp, dry_run=self.config.dry_run)
        self.reporter.changes([*out.changes, *self.navigator.drain_changes()])
        self.observers.cycle(out, self.navigator, self.perception)
        self._check_done(now)
        return out

    def _check_done(self, now: float) -> None:
        """Note the end of a flight (its flight time stops there); with ``exit_when_done`` it ends the run."""
        cfg = self.config
        exits = cfg.exit_when_done
        # Without exit_when_done the limits do not apply: the service waits for its autopilot and its goal for ever.
        limits = {"max_s": cfg.max_flight_s, "max_lost_s": cfg.max_link_lost_s} if exits else {"max_s": 0.0}
        if self.flight.check(now, self.navigator, goals=self.counters.goals, ends_run=exits, **limits) and exits:
            if self.flight.outcome is Outcome.LINK_LOST:
                _log_link_lost(self, now, ends_run=True)
            self._stop.set()

    async def _periodic(self, task: str, due: Callable[[float], float], retry_s: float) -> None:
        """``due(now)`` sends what is due and returns when to call it again (``retry_s`` later if it raised)."""
        while True:
            now = self.clock.now()
            try:
                next_s = due(now)
            except Exception as err:
                self.faults.caught(task, err)
                next_s = now + retry_s
            await self.clock.sleep(next_s - now)

    async def _takeover_loop(self) -> None:
        while True:
            await self.clock.sleep(self.takeover.controller.poll_interval_s)
            try:
                self.takeover.step(self.clock.now())
            except Exception as err:
                self.faults.caught("takeover", err)


class TakeoverDriver:
    """Steps the pure ``TakeoverController`` with what the other parts know and carries out its actions."""

    def __init__(
        self,
        controller: TakeoverController,
        *,
        navigator: Navigator,
        handlers: AutopilotHandlers,
        outbox: Outbox,
        reporter: StatusReporter,
        profile: Autopilot,
    ) -> None:
        self.controller = controller
        self.navigator = navigator
        self.handlers = handlers
        self.outbox = outbox
        self.reporter = reporter
        self.profile = profile

    def step(self, now: float) -> None:
        """Step the takeover controller with what is known now and carry out its actions."""
        nav, ap = self.navigator, self.handlers
        pose = nav.pose
        inputs = TakeoverInputs(
            navigating=nav.state is State.NAVIGATING,
            engaged=nav.engaged,
            route=nav.route,
            mode_ok=ap.mode_ok,
            armed=ap.armed,
            down_m=None if pose is None else float(pose.pos_ned_m[2]),
            home_amsl_m=ap.home_amsl_m(),
            waiting=nav.state is State.HOLDING and not nav.engaged,
            ekf_ready=ap.ekf_ready,
            heartbeats=ap.heartbeats,
            acks=ap.acks,
        )
        for action in self.controller.step(now, inputs):
            self._carry_out(action, now)

    def _carry_out(self, action: Action, now: float) -> None:
        kind, profile = action.kind, self.profile
        if kind is ActionKind.SET_MODE:
            self.reporter.counters.mode_requests += 1
            self.outbox.set_mode(profile)
        elif kind is ActionKind.ARM:
            self.outbox.arm()
        elif kind is ActionKind.TAKEOFF:
            self.outbox.takeoff(action.value)
        elif kind is ActionKind.SUSPEND:
            self.navigator.suspend()  # no setpoints while arming / taking off
        elif kind is ActionKind.RESUME:
            self.navigator.resume()
        elif kind is ActionKind.FAILED:
            log.warning("takeover.failed", extra={"error": action.reason})
            self.navigator.resume()
            self.navigator.clear_route(now, f"takeover failed: {action.reason}")  # reported by the next cycle
        elif kind is ActionKind.ABANDONED:
            log.info("takeover.abandoned", extra={"reason": action.reason})  # the new goal's takeover follows
        else:
            log.info(f"takeover.{kind.value}", extra={"profile": profile.value, "down_m": action.value})


class ZenohInputs:
    """Scans (to perception) and goals (to goal admission) from zenoh."""

    def __init__(self, zenoh: Any, section: ZenohSection, service: CompanionService) -> None:
        self.zenoh = zenoh
        self.section = section
        self.service = service

    async def run(self) -> None:
        zc, svc = self.section, self.service
        async for sample in self.zenoh.samples():
            now = svc.clock.now()
            try:
                if sample.key_expr == zc.goal_key:
                    self._goal(sample.payload, now)
                elif sample.key_expr == zc.sensor_key:
                    svc.perception.on_scan_payload(sample.encoding, sample.payload, now)
                else:
                    svc.counters.foreign_messages += 1
            except Exception as err:
                svc.faults.caught("zenoh", err)

    def _goal(self, payload: bytes, now: float) -> None:
        try:
            goal = decode_goal_json(payload)
        except (ProtocolError, ConfigError) as err:
            self.service.counters.bad_goals += 1
            log.info("goal.rejected", extra={"source": "zenoh", "error": str(err)})
            return
        p = goal.pos_ned_m
        self.service.admission.admit(Route.point(float(p[0]), float(p[1]), float(p[2]), source="zenoh"), now)


def _open_observers(config: ServiceConfig, clock: ServiceClock) -> list[CycleObserver]:
    """The Foxglove sink when ``[visualisation]`` asks for one (foxglove-sdk is imported only then)."""
    vc = config.visualisation
    if not vc.enabled:
        return []
    try:
        from apf_companion.viz.sink import FoxgloveSink, mcap_path_in
    except ImportError as err:  # the optional extra is missing
        msg = "[visualisation] needs foxglove-sdk: pip install 'apf-companion[viz]'"
        raise ConfigError(msg) from err

    mcap = mcap_path_in(config.resolve(vc.mcap_dir)) if vc.mcap_dir else None
    port = vc.foxglove_port if vc.foxglove else None
    return [FoxgloveSink(mcap_path=mcap, port=port, t0_s=clock.now())]


def _optional_tasks(svc: CompanionService) -> list[tuple[str, Coroutine[Any, Any, None]]]:
    """The service's tasks that run only when configured: forwarding, zenoh inputs, the signing timestamp."""
    out: list[tuple[str, Coroutine[Any, Any, None]]] = []
    if svc.forwarder.params.enabled:
        out.append(("apf.forward", svc._periodic("forward", svc.forwarder.due, svc.forwarder.period_s)))
    if svc.zenoh is not None:
        out.append(("apf.zenoh", ZenohInputs(svc.zenoh, svc.config.zenoh, svc).run()))
    if svc.signing_keeper is not None:
        out.append(("apf.signing", svc.signing_keeper.run(lambda err: svc.faults.caught("signing", err))))
    if svc.fence is not None:
        out.append(("apf.fence", svc._periodic("fence", svc.fence.due, STEP_S)))
    return out


async def _open_mavlink(config: ServiceConfig) -> tuple[MavlinkLink, TimestampKeeper | None]:
    """The autopilot link, signed when ``[link] signing_key_file`` is set (then with its timestamp keeper, which
    has saved once: an unwritable timestamp file is a start-up error, not a surprise 30 s later)."""
    lc = config.link
    signing = signing_setup(config)  # key and timestamp files are checked before any socket is opened
    link = await MavlinkLink.open(
        lc.connect,
        source_system=lc.autopilot_sysid,
        source_component=lc.component_id,
        tlog_path=config.resolve(lc.tlog) if lc.tlog else None,
        signing=None if signing is None else signing.params,
    )
    if signing is None or link.signing is None:
        return link, None
    keeper = TimestampKeeper(link.signing, signing.timestamps)
    try:
        keeper.save()
    except OSError as err:
        await link.aclose()
        msg = f"cannot write signing timestamp file {signing.timestamps.path}: {err.strerror}"
        raise ConfigError(msg) from err
    log.info("signing.on", extra={"timestamp": link.signing.timestamp, "timestamp_file": str(keeper.store.path)})
    return link, keeper


def _goal_admission(svc: CompanionService, start_route: Route | None) -> GoalAdmission:
    """Goal admission with the bounds in effect at each check: the fence read so far, the planner in service."""

    def bounds() -> GoalBounds:
        fence = None if svc.fence is None else svc.fence.bounds
        return GoalBounds(fence=fence, area_ne_m=flying_area(svc.planner), keepouts_ne_m=keepout_zones(svc.planner))

    return GoalAdmission(
        admission_params(svc.config),
        navigator=svc.navigator,
        bounds=bounds,
        counters=svc.counters,
        flight=svc.flight,
        statustext=svc.statustext,
        end_run=svc.stop,
        start_route=start_route,
    )


def _param_server(svc: CompanionService) -> ParamServer:
    """The service's parameter server: the PARAM_SETs accepted since the last cycle go into service before the next
    one (``run_cycle``: ``ParamServer.apply_pending``), with one planner build for them all."""

    def apply(config: ServiceConfig, planner: Any) -> None:
        _put_in_service(svc, config, planner)

    return ParamServer(
        svc.config,
        svc.planner.params,
        outbox=svc.outbox,
        apply=apply,
        statustext=svc.reporter.statustext,
        counters=svc.counters,
    )


def _put_in_service(svc: CompanionService, config: ServiceConfig, planner: Any) -> None:
    """A changed config and its planner (a PARAM_SET, the fence's area) into service between two cycles; the
    navigator calls the planner through the observers' tap, as at start (the recording sees its decisions)."""
    svc.config, svc.planner = config, planner
    reconfigure(svc.navigator, navigator_params(config, planner), svc.observers.tap(planner))
    if svc.fence is not None:  # APF_FENCE_POLL: the next read is due fence_poll_s after the last one ended
        svc.fence.params = dataclasses.replace(svc.fence.params, poll_s=config.planner.fence_poll_s)


def _fence_reader(svc: CompanionService) -> FenceReader | None:
    """The fence download when ``planner.fence_area`` asks for it: bapf-nav, no area and no keep-out zones in the
    config (the config's own zones win), a link."""
    config = svc.config
    if fence_not_read(config, svc.planner) is not None or svc.outbox.silent:  # e.g. the config's own zones win
        return None
    lc = config.link
    params = FenceReaderParams(
        our_system=lc.autopilot_sysid,
        our_component=lc.component_id,
        autopilot=Source(lc.autopilot_sysid, lc.autopilot_compid),
        profile=config.autopilot.profile,
        poll_s=config.planner.fence_poll_s,
    )

    def where() -> tuple[GlobalReference, tuple[float, float]] | None:
        ref, pose = svc.handlers.global_ref, svc.navigator.pose
        if ref is None or pose is None:
            return None
        return ref, (float(pose.pos_ned_m[0]), float(pose.pos_ned_m[1]))

    def clearance_m() -> float:  # bapf-nav's C: it keeps that much of the fence's margin already
        return svc.planner.params.clearance_m if isinstance(svc.planner, BapfNavPlanner) else 0.0

    return FenceReader(
        params, outbox=svc.outbox, reference=where, on_area=lambda area: _use_fence(svc, area), clearance_m=clearance_m
    )


def _use_fence(svc: CompanionService, area: FenceArea) -> None:
    """The fence's zones become bapf-nav's flying area and keep-out zones, as a PARAM_SET would change a parameter
    (between cycles: the goal is kept, the next cycle plans over them). Called at the first read and whenever the
    fence changed: a new fence replaces the old one's zones; a fence removed, or one that is not used, takes them
    out of service (the autopilot no longer enforces the old one). A fence that is not used is logged and said in
    a STATUSTEXT (the ground station's user set it up); no fence at the first read is only logged. A goal taken
    before these bounds were known is checked against them (``GoalAdmission.recheck``)."""
    svc.admission.recheck(svc.clock.now())
    in_service = has_zones(svc.planner)
    if area.outcome is FenceOutcome.USED:
        try:
            _put_fence_in_service(svc, area)
        except ConfigError as err:  # e.g. wider than 256 cells of nav_cell_m
            area = FenceArea(FenceOutcome.NOT_USED, str(err))
        else:
            zones = {k: v for k, v in svc.config.planner.params.items() if k in ("nav_area_ne_m", "nav_keepout_ne_m")}
            changed = svc.fence is not None and svc.fence.changes > 0
            log.info("fence.area", extra={"note": area.note, "changed": changed, **zones})
            verb = "changed" if changed else "area"
            svc.reporter.statustext(mavlink.MAV_SEVERITY_INFO, f"fence {verb}: {area.note}")
            return
    if in_service:
        _put_fence_in_service(svc, area)  # no zones: cannot fail
    if area.outcome is FenceOutcome.NO_FENCE:
        log.info("fence.none", extra={"note": area.note, "removed": in_service})
        if in_service:
            svc.reporter.statustext(mavlink.MAV_SEVERITY_NOTICE, "fence removed: planning without a flying area")
        return
    log.warning("fence.not_used", extra={"outcome": area.outcome.value, "reason": area.note})
    svc.reporter.statustext(mavlink.MAV_SEVERITY_NOTICE, f"fence not used: {area.note}")


def _put_fence_in_service(svc: CompanionService, area: FenceArea) -> None:
    """The config with the fence's zones (none: the config as it was without a fence) and its planner into
    service, with the PARAM_SETs accepted since the last cycle; a later PARAM_SET starts from it. ConfigError when
    the planner refuses the zones."""
    config = config_with_fence(svc.params.config, area)
    planner = build_planner(config)
    svc.params.taken(config, planner)  # puts it into service (``_put_in_service``)


def _warn_no_heartbeat(svc: CompanionService) -> None:
    """Nothing heard from the autopilot yet: a WARNING with what to check for this link."""
    lc = svc.config.link
    heard_others = svc.link is not None and svc.link.stats.packets_received > 0
    hint = (
        f"messages arrive but none from the autopilot: check link.autopilot_sysid ({lc.autopilot_sysid}) and "
        f"link.autopilot_compid ({lc.autopilot_compid}) (ArduPilot SYSID_THISMAV, PX4 MAV_SYS_ID)"
        if heard_others
        else connection_hint(parse_endpoint(lc.connect))
    )
    extra = {"connect": lc.connect, "waited_s": round(svc.clock.now(), 1), "hint": hint}
    log.warning("link.no_heartbeat", extra=extra)


def _status_text(svc: CompanionService) -> str:
    return f"{svc.navigator.state.value}: {svc.reporter.reason}"


def _sd_notify(svc: CompanionService, **fields: str | int) -> None:
    if svc.notifier is not None:
        svc.notifier.notify(**fields)


def _log_setpoint(out: CycleOutput, sp: Setpoint, *, dry_run: bool) -> None:
    extra = {"state": out.state.value, "kind": sp.kind.value, "pos_ned_m": sp.pos_ned_m}
    log.debug(
        "cycle.setpoint", extra=extra | {"vel_ned_m_s": sp.vel_ned_m_s, "decision": out.decision, "dry_run": dry_run}
    )


def _status_due(svc: CompanionService) -> Callable[[float], float]:
    """The status task's schedule: the reporter's, and the warnings while the autopilot is silent."""
    warning, no_pose, lost = NoHeartbeatWarning(svc), DryRunNoPoseWarning(svc), LinkLostLog(svc)
    return lambda now: min(svc.reporter.due(now), warning.due(now), no_pose.due(now), lost.due(now))


def _log_link_lost(svc: CompanionService, now_s: float, *, ends_run: bool = False) -> None:
    """One WARNING while LINK_LOST: how long no autopilot HEARTBEAT came, whether the goal waits for its return,
    and (``exit_when_done``) after how long the run ends; ``ends_run``: it ends now (outcome link_lost)."""
    nav, cfg = svc.navigator, svc.config
    lost_s = nav.heartbeat_age_s(now_s)
    extra: dict[str, Any] = {
        "lost_s": None if lost_s is None else round(lost_s, 1),
        "goal": "kept" if nav.has_goal else "none",
        "connect": cfg.link.connect,
        "ends_run": ends_run,
    }
    if cfg.exit_when_done and cfg.max_link_lost_s > 0:
        extra["max_link_lost_s"] = cfg.max_link_lost_s
    log.warning("link.lost", extra=extra)


class LinkLostLog:
    """While LINK_LOST (after the ``state.change`` line): a WARNING every ``LINK_LOST_REPEAT_S`` saying how long
    (``_log_link_lost``), so that a log that goes quiet is not read as a hung service. ``due`` fits
    ``CompanionService._periodic``."""

    def __init__(self, svc: CompanionService) -> None:
        self.svc = svc
        self.next_s = math.inf  # the next line, while LINK_LOST

    def due(self, now_s: float) -> float:
        if self.svc.navigator.state is not State.LINK_LOST:
            self.next_s = math.inf
            return now_s + 1.0  # look again in a second (the status task wakes at 1 Hz for the HEARTBEAT anyway)
        if self.next_s == math.inf:
            self.next_s = now_s + LINK_LOST_REPEAT_S
        elif now_s >= self.next_s:
            self.next_s = now_s + LINK_LOST_REPEAT_S
            _log_link_lost(self.svc, now_s)
        return self.next_s


class NoHeartbeatWarning:
    """Nothing heard from the autopilot: a WARNING with what to check, ``NO_HEARTBEAT_WARN_S`` after the start and
    then every ``NO_HEARTBEAT_REPEAT_S`` while it stays silent. ``due`` fits ``CompanionService._periodic``."""

    def __init__(self, svc: CompanionService) -> None:
        self.svc = svc
        self.warn_at_s = svc.clock.now() + NO_HEARTBEAT_WARN_S

    def due(self, now_s: float) -> float:
        if self.svc.handlers.heard:
            return math.inf
        if now_s >= self.warn_at_s:
            self.warn_at_s = now_s + NO_HEARTBEAT_REPEAT_S
            _warn_no_heartbeat(self.svc)
        return self.warn_at_s


class DryRunNoPoseWarning:
    """A dry run asks for no streams, and an autopilot that streams nothing unasked (ArduPilot's default) leaves it
    HOLDING with "no pose yet": one WARNING saying so (``DRY_RUN_NO_POSE_HINT``), ``DRY_RUN_NO_POSE_WARN_S`` after
    the start and ``DRY_RUN_NO_POSE_AFTER_HEARD_S`` after the first HEARTBEAT, when no LOCAL_POSITION_NED came.
    Without a HEARTBEAT ``NoHeartbeatWarning`` speaks. ``due`` fits ``CompanionService._periodic``."""

    def __init__(self, svc: CompanionService) -> None:
        self.svc = svc
        self.warn_at_s = svc.clock.now() + DRY_RUN_NO_POSE_WARN_S if svc.config.dry_run else math.inf
        self.heard_at_s: float | None = None

    def due(self, now_s: float) -> float:
        if self.warn_at_s == math.inf or self.svc.perception.counters.poses > 0:
            self.warn_at_s = math.inf
            return math.inf
        if not self.svc.handlers.heard:
            return now_s + 1.0
        if self.heard_at_s is None:
            self.heard_at_s = now_s
            self.warn_at_s = max(self.warn_at_s, now_s + DRY_RUN_NO_POSE_AFTER_HEARD_S)
        if now_s >= self.warn_at_s:
            self.warn_at_s = math.inf
            extra = {"connect": self.svc.config.link.connect, "waited_s": round(now_s, 1), "hint": DRY_RUN_NO_POSE_HINT}
            log.warning("dry_run.no_pose", extra=extra)
        return self.warn_at_s


async def _open_zenoh(config: ServiceConfig) -> Any:
    """Open the zenoh session and subscribe: sensor topic latest-wins, goal topic FIFO (bounded)."""
    from apf_companion.links.zenoh import Overflow, ZenohConfig, open_with_retry

    zc = config.zenoh
    config_file = str(config.resolve(zc.config_file)) if zc.config_file else None
    link = await open_with_retry(
        ZenohConfig(mode=zc.mode, connect=zc.connect, listen=zc.listen, config_file=config_file),
        total_s=zc.router_wait_s,
    )
    try:
        if config.sensors.zenoh:
            await link.subscribe(zc.sensor_key, overflow=Overflow.LATEST_PER_KEY, capacity=4)
        await link.subscribe(zc.goal_key, overflow=Overflow.FIFO, capacity=16)
    except BaseException:
        await link.aclose()
        raise
    return link
