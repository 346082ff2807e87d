"""The autopilot handlers: decoded MAVLink records in, to the part that owns what they carry.

Messages are accepted only from the configured autopilot (sysid/compid), one handler per record type
(``_from_autopilot``); the exceptions (``_from_others``) come from a configured ground-station sysid and are
addressed to us: COMMAND_INT / COMMAND_LONG (DO_REPOSITION) and the parameter protocol (PARAM_*, to ``on_param``).
"To us" is our sysid (the vehicle's) or 0 (broadcast, MAVProxy's default) and our component or 0 (all
components). Range messages come from the autopilot or a configured sensor (``[sensors] mavlink_sources``); from
anyone else they are counted in ``rejected_ranges``, everything else in ``foreign_messages``; both are dropped.

``AutopilotHandlers`` is the dispatcher the service uses; its parts (apf_companion/handling/) each own their state:

- ``AutopilotState`` (vehicle.py): the autopilot's mode and arming (HEARTBEAT), whether it has been heard, its EKF
  flags and its COMMAND_ACKs; the route at start, or the hold of a restart mid-flight.
- ``StreamRequests`` (streams.py): the telemetry streams asked for (``StreamKeeper``) and the slow-stream log.
- ``GlobalPlacement`` (globalref.py): the global reference (GLOBAL_POSITION_INT) that places global goals and the
  PX4 takeoff altitude.
- ``PoseRouting``, ``RangeRouting`` (poses.py): poses and ranges to the perception front end, poses on to the
  navigator; the proximity echo of our own forwarded obstacles dropped.
- ``GoalCommands`` (goals.py): DO_REPOSITION and the autopilot's guided target (goal adoption).

The fence read's records (``on_fence``) and the parameter protocol (``on_param``) go to the callbacks given.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from apf_companion.goal import GlobalReference, Route
from apf_companion.handling.globalref import GlobalPlacement
from apf_companion.handling.goals import GoalCommands
from apf_companion.handling.params import BROADCAST, HandlerParams
from apf_companion.handling.poses import PoseRouting, RangeRouting
from apf_companion.handling.streams import StreamRequests
from apf_companion.handling.vehicle import AutopilotState
from apf_companion.links.messages import (
    Attitude,
    CommandAck,
    CommandInt,
    CommandLong,
    DistanceSensor,
    EkfStatusReport,
    FenceRecord,
    GlobalPositionInt,
    Heartbeat,
    HomePosition,
    LocalPositionNed,
    MissionAck,
    MissionCount,
    MissionCurrent,
    MissionItemInt,
    ObstacleDistance,
    ObstacleDistance3d,
    Odometry,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    PositionTargetGlobalInt,
    PositionTargetLocalNed,
    Record,
    Source,
    SysStatus,
)
from apf_companion.navigator import Navigator
from apf_companion.outbox import Outbox
from apf_companion.perception import PerceptionFrontEnd
from apf_companion.reporter import ServiceCounters
from apf_companion.streams import StreamKeeper

__all__ = ["COMMAND_MESSAGES", "AutopilotHandlers", "HandlerParams"]

#: Messages that ask for action (goals, modes, parameter changes): with a signing key they are used only when signed
#: with it (``link.require_signed_commands``; the link drops the others before any handler sees them). PARAM_SET
#: changes the planner's and the navigator's safety parameters (apf_companion.params); until session 28 it was
#: missing here and an unsigned one set the safety margin to 0. The parameter reads (PARAM_REQUEST_LIST / _READ)
#: change nothing and answer with values that are no secret (the config's), so they follow the telemetry rule.
COMMAND_MESSAGES = (
    "COMMAND_INT",
    "COMMAND_LONG",
    "SET_POSITION_TARGET_LOCAL_NED",
    "SET_POSITION_TARGET_GLOBAL_INT",
    "SET_MODE",
    "PARAM_SET",
)
RANGE_RECORDS = (ObstacleDistance, DistanceSensor, ObstacleDistance3d)
FENCE_RECORDS = (MissionCount, MissionCurrent, MissionItemInt, MissionAck, ParamValue, HomePosition, SysStatus)
ParamRecord = ParamRequestList | ParamRequestRead | ParamSet
Handler = Callable[[Any, float], None]


class AutopilotHandlers:
    """Routes decoded records (see the module docstring) and answers what the others read of the autopilot.

    Args:
        set_route: Offers a goal to goal admission (``GoalAdmission.admit``; False: refused).
        on_pose: Called with the autopilot's ``time_boot_ms`` when the navigator accepted a new pose (it triggers
            a cycle, and the stream's gaps measure the link's loss).
        route_at_start: Flown once the autopilot is first heard.
        on_param: Handles a PARAM_* addressed to us, with the time (apf_companion.params.ParamServer.handle); None =
            ignored.
        on_fence: Takes the autopilot's MISSION_COUNT / MISSION_ITEM_INT / MISSION_ACK, PARAM_VALUE,
            HOME_POSITION and SYS_STATUS (the fence read,
            apf_companion.fencereader.FenceReader.on_record); None = ignored.
        statustext: Sends a STATUSTEXT (severity, text) as the reporter does (``StatusReporter.statustext``); None =
            none.
    """

    def __init__(
        self,
        params: HandlerParams,
        *,
        perception: PerceptionFrontEnd,
        navigator: Navigator,
        outbox: Outbox,
        counters: ServiceCounters,
        set_route: Callable[[Route, float], bool],
        on_pose: Callable[[int], None],
        route_at_start: Route | None,
        on_param: Callable[[ParamRecord, float], None] | None = None,
        on_fence: Callable[[FenceRecord], None] | None = None,
        statustext: Callable[[int, str], None] | None = None,
    ) -> None:
        self.params = params
        self.counters = counters
        self._on_param = on_param
        self._fence_sink = on_fence
        self._streams = StreamRequests(params, outbox=outbox, counters=counters)
        self._autopilot = AutopilotState(
            params,
            gate=perception.gate,
            navigator=navigator,
            streams=self._streams,
            set_route=set_route,
            route_at_start=route_at_start,
        )
        self._placement = GlobalPlacement(perception=perception, navigator=navigator)
        poses = PoseRouting(
            perception=perception,
            navigator=navigator,
            global_ref=self._placement,
            on_pose=on_pose,
            statustext=statustext or (lambda severity, text: None),
        )
        ranges = RangeRouting(params, perception=perception, counters=counters)
        self._goals = goals = GoalCommands(
            params,
            autopilot=self._autopilot,
            global_ref=self._placement,
            navigator=navigator,
            outbox=outbox,
            counters=counters,
            set_route=set_route,
        )
        #: One handler per record type from the autopilot (commands from it are not for us: ignored).
        self._from_autopilot = self._autopilot_table(poses, ranges, goals)
        #: From anyone else: commands and PARAM_* for us, ranges from a configured sensor; the rest is foreign.
        self._from_others: dict[type[Any], Handler] = (
            dict.fromkeys((CommandInt, CommandLong), self._on_command)
            | dict.fromkeys(RANGE_RECORDS, self._on_sensor_range)
            | dict.fromkeys((ParamRequestList, ParamRequestRead, ParamSet), self._on_param_record)
        )

    def _autopilot_table(
        self, poses: PoseRouting, ranges: RangeRouting, goals: GoalCommands
    ) -> dict[type[Any], Handler]:
        """The handler of each record type from the autopilot, in the parts that own what it changes."""
        return {
            Heartbeat: self._autopilot.on_heartbeat,
            EkfStatusReport: self._autopilot.on_ekf_status,
            CommandAck: self._autopilot.on_command_ack,
            LocalPositionNed: poses.on_local_position,
            Attitude: poses.on_attitude,
            Odometry: poses.on_odometry,
            GlobalPositionInt: self._placement.on_global_position,
            ObstacleDistance: ranges.on_obstacle_distance,
            DistanceSensor: ranges.on_distance_sensor,
            ObstacleDistance3d: ranges.on_obstacle_distance_3d,
            PositionTargetLocalNed: goals.on_position_target_local,
            PositionTargetGlobalInt: goals.on_position_target_global,
            **dict.fromkeys(FENCE_RECORDS, self._on_fence),
        }

    def handle(self, rec: Record, now_s: float) -> None:
        if rec.src == self.params.autopilot:
            self._streams.heard(rec, now_s)
            handler = self._from_autopilot.get(type(rec))
            if handler is not None:
                handler(rec, now_s)
        else:
            self._from_others.get(type(rec), self._foreign)(rec, now_s)

    def undecoded(self, consumed: bool, src: Source | None) -> None:
        """A message without a record: malformed if its type is consumed; else foreign unless from the autopilot."""
        if consumed:
            self.counters.undecodable_messages += 1
        elif src != self.params.autopilot:
            self.counters.foreign_messages += 1

    def _for_us(self, rec: CommandInt | CommandLong | ParamRecord) -> bool:
        """From a ground station, to our system (or all) and our component (or all): MAVLink routing's rule."""
        p = self.params
        return (
            rec.src.system in p.gcs_sysids
            and rec.target_system in (p.autopilot.system, BROADCAST)
            and rec.target_component in (p.component_id, BROADCAST)
        )

    def _on_command(self, rec: CommandInt | CommandLong, now_s: float) -> None:
        if self._for_us(rec):
            self._goals.on_command(rec, now_s)
        else:
            self._foreign(rec, now_s)

    def _on_sensor_range(self, rec: Record, now_s: float) -> None:
        if rec.src in self.params.sensor_sources:
            self._from_autopilot[type(rec)](rec, now_s)
        else:
            self.counters.rejected_ranges += 1

    def _on_param_record(self, rec: ParamRecord, now_s: float) -> None:
        if self._on_param is not None and self._for_us(rec):
            self.counters.param_requests += 1
            self._on_param(rec, now_s)
        else:
            self._foreign(rec, now_s)

    def _on_fence(self, rec: FenceRecord, now_s: float) -> None:
        if self._fence_sink is not None:
            self._fence_sink(rec)

    def _foreign(self, rec: Record, now_s: float) -> None:
        self.counters.foreign_messages += 1

    @property
    def heard(self) -> bool:
        return self._autopilot.heard

    @property
    def heartbeats(self) -> int:
        return self._autopilot.heartbeats

    @property
    def armed(self) -> bool:
        return self._autopilot.armed

    @property
    def mode_ok(self) -> bool:
        return self._autopilot.mode_ok

    @property
    def ekf_ready(self) -> bool:
        return self._autopilot.ekf_ready

    @property
    def acks(self) -> dict[int, tuple[int, float]]:
        return self._autopilot.acks

    @property
    def streams(self) -> StreamKeeper:
        return self._streams.keeper

    @property
    def global_ref(self) -> GlobalReference | None:
        return self._placement.global_ref

    def home_amsl_m(self) -> float | None:
        return self._placement.home_amsl_m()
