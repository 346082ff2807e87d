"""The autopilot handlers: decoded MAVLink records in, to the part that owns what they carry.

Messages are accepted only from the configured autopilot (sysid/compid), one handler per record type
(``_AUTOPILOT``); the exceptions come from a configured ground-station sysid and are addressed to us: COMMAND_INT /
COMMAND_LONG (DO_REPOSITION) and the parameter protocol (PARAM_*, to ``on_param``). "To us" is our sysid (the
vehicle's) or 0 (broadcast, MAVProxy's default) and our component or 0 (all components). Range messages come from
the autopilot or a configured sensor (``[sensors] mavlink_sources``); from anyone else they are counted in
``rejected_ranges``, everything else in ``foreign_messages``; both are dropped.

While the service forwards its obstacles (OBSTACLE_DISTANCE), the autopilot's DISTANCE_SENSOR with ids 10-18 is
its proximity library reporting those same sectors back (``GCS_Common.cpp`` ``send_proximity``:
``PROXIMITY_SENSOR_ID_START + i``); reading it would keep every forwarded obstacle alive forever, so it is
counted (``proximity_echoes_ignored``) and dropped.

Owns what the autopilot says about itself: its mode and arming (HEARTBEAT), whether it has been heard, and the
global reference (GLOBAL_POSITION_INT) that places global goals and the PX4 takeoff altitude.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.adopt import ECHO_WINDOW_S, AdoptParams, is_new_target
from apf_companion.autopilot import Autopilot, CopterMode, Px4MainMode, Px4Mode
from apf_companion.goal import GlobalReference, RepositionError, Route, local_goal_from_reposition
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
from apf_companion.perception import PerceptionFrontEnd, euler_yaw_rate_rad_s
from apf_companion.perception.ratelog import RateLimitedLog
from apf_companion.reporter import ServiceCounters
from apf_companion.streams import StreamKeeper, wanted_streams

__all__ = ["COMMAND_MESSAGES", "AutopilotHandlers", "HandlerParams", "mode_is_ours"]

log = logging.getLogger(__name__)

NOT_A_VEHICLE = frozenset({mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GCS})  # their HEARTBEATs
REBOOTING = frozenset({mavlink.MAV_STATE_UNINIT, mavlink.MAV_STATE_BOOT})  # HEARTBEAT.system_status
RANGE_RECORDS = (ObstacleDistance, DistanceSensor, ObstacleDistance3d)
# AP_Proximity.h PROXIMITY_SENSOR_ID_START (10): DISTANCE_SENSOR ids of the proximity sectors (8) and upward (+9)
PROXIMITY_ECHO_IDS = range(10, 10 + 9)
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
BROADCAST = 0  # target_system / target_component 0: every system / every component (MAVLink routing)
ParamRecord = ParamRequestList | ParamRequestRead | ParamSet
DEG_E7 = 1e-7
MM = 1e-3
# ArduCopter position_ok() (system.cpp ekf_has_absolute_position / _relative_position): a horizontal position, not
# the constant-position mode the EKF is in before it has one
#: STATUSTEXT when two pose streams with the autopilot's ids disagree (``PoseGate`` CONFLICT): the service brakes.
POSE_CONFLICT_TEXT = "APF BRAKING: two position streams disagree"
SLOW_STREAMS_LOG_INTERVAL_S = 60.0  # ``streams.slow``: the first at once, then at most one line a minute
EKF_POSITION_FLAGS = mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS | mavlink.EKF_POS_HORIZ_REL
_STREAM_OF = {
    LocalPositionNed: mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    Attitude: mavlink.MAVLINK_MSG_ID_ATTITUDE,
    GlobalPositionInt: mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    EkfStatusReport: mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
    SysStatus: mavlink.MAVLINK_MSG_ID_SYS_STATUS,
}


def mode_is_ours(profile: Autopilot, custom_mode: int) -> bool:
    """HEARTBEAT.custom_mode is GUIDED (ArduCopter) / OFFBOARD (PX4)."""
    if profile is Autopilot.ARDUPILOT:
        return custom_mode == CopterMode.GUIDED
    return Px4Mode.from_custom_mode(custom_mode).main == Px4MainMode.OFFBOARD


@dataclass(frozen=True, slots=True, kw_only=True)
class HandlerParams:
    autopilot: Source
    component_id: int = 191  # ours
    gcs_sysids: tuple[int, ...] = (255,)
    profile: Autopilot = Autopilot.ARDUPILOT
    dry_run: bool = False
    mavlink_ranges: bool = True  # [sensors] mavlink
    telemetry_rate_hz: float = 20.0
    sensor_sources: tuple[Source, ...] = ()  # [sensors] mavlink_sources
    forwarding: bool = False  # [sensors] forward_obstacle_distance
    adopt: AdoptParams = field(default_factory=AdoptParams)
    fly_config_goal_after_restart: bool = False  # [goal] fly_after_restart


class AutopilotHandlers:
    """Routes decoded records (see the module docstring).

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
        self.perception = perception
        self.navigator = navigator
        self.outbox = outbox
        self.counters = counters
        self._set_route = set_route
        self._on_pose = on_pose
        self._route_at_start = route_at_start
        self._on_param = on_param
        self._fence_sink = on_fence
        self._statustext = statustext or (lambda severity, text: None)
        self.heard = False
        self.heartbeats = 0  # autopilot HEARTBEATs heard (the takeover weighs its evidence by them)
        self.custom_mode: int | None = None
        self.base_mode = 0
        self.global_ref: GlobalReference | None = None
        #: A GLOBAL_POSITION_INT waiting for the pose of its time: (time_boot_ms, lat, lon [deg], alt, rel [m]).
        self._pending_global: tuple[int, float, float, float, float] | None = None
        self.streams = StreamKeeper(
            wanted_streams(params.profile, params.telemetry_rate_hz, targets=params.adopt.enabled)
        )
        self._slow_log = RateLimitedLog(log, "streams.slow", SLOW_STREAMS_LOG_INTERVAL_S)
        self.ekf_flags: int | None = None  # latest EKF_STATUS_REPORT.flags; None: the autopilot sends none
        self.acks: dict[int, tuple[int, float]] = {}  # command -> (result, service time) of its latest ACK to us

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode_ok(self) -> bool:
        """The autopilot's latest mode is ours (GUIDED / OFFBOARD); False before its first HEARTBEAT."""
        return self.custom_mode is not None and mode_is_ours(self.params.profile, self.custom_mode)

    @property
    def ekf_ready(self) -> bool:
        """The EKF has a horizontal position; True when the autopilot reports no EKF status (PX4)."""
        return self.ekf_flags is None or (
            bool(self.ekf_flags & EKF_POSITION_FLAGS) and not self.ekf_flags & mavlink.EKF_CONST_POS_MODE
        )

    def handle(self, rec: Record, now_s: float) -> None:
        if rec.src == self.params.autopilot:
            stream = _STREAM_OF.get(type(rec))
            if stream is not None:
                self.streams.heard(stream, now_s)
            handler = _AUTOPILOT.get(type(rec))
            if handler is not None:
                handler(self, rec, now_s)
        elif isinstance(rec, CommandInt | CommandLong) and self._for_us(rec):
            self._on_command(rec, now_s)
        elif isinstance(rec, RANGE_RECORDS):
            if rec.src in self.params.sensor_sources:
                _AUTOPILOT[type(rec)](self, rec, now_s)
            else:
                self.counters.rejected_ranges += 1
        elif isinstance(rec, ParamRecord) and self._on_param is not None and self._for_us(rec):
            self.counters.param_requests += 1
            self._on_param(rec, now_s)
        else:
            self.counters.foreign_messages += 1

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

    # ---- from the autopilot ------------------------------------------------------------------------------------
    def _on_heartbeat(self, rec: Heartbeat, now_s: float) -> None:
        if rec.type in NOT_A_VEHICLE:
            return
        at_start = not self.heard  # this process's first HEARTBEAT
        first = at_start or not self.navigator.link_alive(now_s)
        if (self.heard and first) or rec.system_status in REBOOTING:
            self.perception.gate.note_reboot()  # boot evidence: a pose may start a new time base
        if first or rec.system_status in REBOOTING:
            self.streams.restart()  # a rebooted autopilot has forgotten our stream requests
        self.heard = True
        self.heartbeats += 1
        self.custom_mode = rec.custom_mode
        self.base_mode = rec.base_mode
        self.navigator.autopilot_heartbeat(now_s, mode_ok=self.params.dry_run or self.mode_ok)
        rates = self.streams.due(now_s)
        if rates:
            self.outbox.request_streams(rates)
            if self.streams.last_slow:
                self._streams_slow(now_s)
        if first:
            route, self._route_at_start = self._route_at_start, None
            restarted = self._restarted_mid_flight(route) if at_start else None
            if restarted is not None:
                self.navigator.recovery.restart_hold(now_s, restarted)
            elif route is not None:
                self._set_route(route, now_s)

    def _streams_slow(self, now_s: float) -> None:
        """Asked again for streams that arrived too slowly: counted, and said (rate-limited) with the likely cause."""
        self.counters.slow_streams += 1
        slow = {
            _message_name(i): f"{hz:.1f} of {self.streams.rates_hz[i]:g} Hz" for i, hz in self.streams.last_slow.items()
        }
        self._slow_log.note(
            now_s,
            streams=slow,
            hint="something on this link lowered the rates, e.g. a ground station's REQUEST_DATA_STREAM through the "
            "same router; asked again. ArduPilot: SERIALn_OPTIONS bit 12 makes the port ignore such requests",
        )

    def _restarted_mid_flight(self, route: Route | None) -> str | None:
        """At the first HEARTBEAT: the vehicle is already flying (armed) in GUIDED / OFFBOARD, so this process was
        (re)started mid-flight: why it holds instead of moving, or None to go on as usual (docs/hardening.md)."""
        if self.params.dry_run or not (self.armed and self.mode_ok):
            return None
        if route is not None and (self.params.fly_config_goal_after_restart or not route.source.startswith("config")):
            return None  # a goal given now (command line), or the config says its goal is fresh
        why = "started with the vehicle flying in guided control: holding, send a fresh goal"
        return why if route is None else f"{why} (goal.fly_after_restart = false)"

    def _on_local_position(self, rec: LocalPositionNed, now_s: float) -> None:
        pose = self.perception.on_local_position(
            rec.time_boot_ms, (rec.x, rec.y, rec.z), now_s, vel_ned_m_s=(rec.vx, rec.vy, rec.vz)
        )
        reset = self.perception.take_reset()
        if reset is not None:
            self.navigator.recovery.position_reset(now_s, reset)
        if self.perception.take_conflict():  # braking with no state change: say why (the log has the details)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, POSE_CONFLICT_TEXT)
        self.navigator.recovery.pose_confirmed = self.perception.gate.confirmed
        if pose is not None and self.navigator.update_pose(pose):
            self._on_pose(rec.time_boot_ms)
        self._place_global(now_s)

    def _on_odometry(self, rec: Odometry, now_s: float) -> None:
        self.perception.gate.note_reset_counter(rec.reset_counter)  # estimator reset evidence for the pose gate

    def _on_attitude(self, rec: Attitude, now_s: float) -> None:
        rate = euler_yaw_rate_rad_s(rec.roll, rec.pitch, rec.pitchspeed, rec.yawspeed)
        self.perception.on_attitude(rec.yaw, time_boot_ms=rec.time_boot_ms, yaw_rate_rad_s=rate)

    def _on_global_position(self, rec: GlobalPositionInt, now_s: float) -> None:
        if self.navigator.pose is None:
            return
        lat, lon = rec.lat * DEG_E7, rec.lon * DEG_E7
        alt, rel = rec.alt * MM, rec.relative_alt * MM
        if not all(math.isfinite(v) for v in (lat, lon, alt, rel)) or (rec.lat == 0 and rec.lon == 0):
            return
        self._pending_global = (rec.time_boot_ms, lat, lon, alt, rel)
        self._place_global(now_s)

    def _place_global(self, now_s: float) -> None:
        """The global reference from the latest GLOBAL_POSITION_INT and the local position at its own time (the
        pose history, by the autopilot's boot time), not the latest pose: a vehicle at 5 m/s moves 0.5 m in the
        100 ms between the two streams, and every global goal and fence vertex placed with this pair would move
        with it. When the pose of its time has not arrived yet (the two streams of one instant in either order),
        it waits for that pose (``_on_local_position``)."""
        if self._pending_global is None:
            return
        boot_ms, lat, lon, alt, rel = self._pending_global
        latest = self.perception.history.latest()
        t = self.perception.scan_time(boot_ms, now_s)
        if latest is not None and t <= latest.t_s:
            p = (self.perception.history.at(t) or latest).pos_ned_m
        else:  # not in the history (yet, or at all: no heading for the poses); the navigator's pose once it is as new
            pose = self.navigator.pose
            if pose is None or pose.t_s < t:
                return
            p = pose.pos_ned_m
        self.global_ref = GlobalReference(
            lat_deg=lat, lon_deg=lon, alt_amsl_m=alt, alt_rel_m=rel, pos_ned_m=(float(p[0]), float(p[1]), float(p[2]))
        )
        self._pending_global = None

    def _on_ekf_status(self, rec: EkfStatusReport, now_s: float) -> None:
        self.ekf_flags = rec.flags
        self.navigator.ekf_ready = self.ekf_ready  # why there is no pose yet (HOLDING reason)

    def _on_fence(self, rec: FenceRecord, now_s: float) -> None:
        if self._fence_sink is not None:
            self._fence_sink(rec)

    def _on_command_ack(self, rec: CommandAck, now_s: float) -> None:
        if rec.target_component in (0, self.params.component_id):
            self.acks[rec.command] = (rec.result, now_s)

    def _on_obstacle_distance(self, rec: ObstacleDistance, now_s: float) -> None:
        if self.params.mavlink_ranges:
            self.perception.on_obstacle_distance(rec, now_s)

    def _on_distance_sensor(self, rec: DistanceSensor, now_s: float) -> None:
        p = self.params
        if p.forwarding and rec.src == p.autopilot and rec.sensor_id in PROXIMITY_ECHO_IDS:
            self.counters.proximity_echoes_ignored += 1
            return
        if p.mavlink_ranges:
            self.perception.on_distance_sensor(rec, now_s)

    def _on_obstacle_distance_3d(self, rec: ObstacleDistance3d, now_s: float) -> None:
        if self.params.mavlink_ranges:
            self.perception.on_obstacle_distance_3d(rec, now_s)

    # ---- the autopilot's guided target (apf_companion.adopt) -----------------------------------------------------
    def _on_position_target_local(self, rec: PositionTargetLocalNed, now_s: float) -> None:
        if self.params.adopt.enabled and rec.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED:
            self._adopt((rec.x, rec.y, rec.z), rec.type_mask, now_s)

    def _on_position_target_global(self, rec: PositionTargetGlobalInt, now_s: float) -> None:
        if not self.params.adopt.enabled:
            return
        try:  # the frames and the flat-earth placement of DO_REPOSITION (apf_companion.goal)
            route = local_goal_from_reposition(
                frame=rec.coordinate_frame,
                x=rec.lat_int,
                y=rec.lon_int,
                z=rec.alt,
                reference=self.global_ref,
                source="",
            )
        except RepositionError:
            return  # no global reference yet, or a frame we cannot place (terrain): not a goal we can fly
        n, e, d = (float(v) for v in route.waypoints_ned_m[-1])
        self._adopt((n, e, d), rec.type_mask, now_s)

    def _adopt(self, target: tuple[float, float, float], type_mask: int, now_s: float) -> None:
        nav = self.navigator
        if not self.mode_ok:
            return
        new = is_new_target(
            target,
            type_mask,
            sent=self.outbox.sent.since(now_s - ECHO_WINDOW_S),
            goal_ned_m=None if nav.route is None else nav.route.waypoints_ned_m[-1].tolist(),
            pose_ned_m=None if nav.pose is None else nav.pose.pos_ned_m.tolist(),
            tolerance_m=self.params.adopt.tolerance_m,
        )
        if new:
            log.info("goal.adopted", extra={"source": "autopilot", "target_ned_m": list(target)})
            self._set_route(Route.point(*target, source="autopilot-target"), now_s)

    # ---- commands for us ---------------------------------------------------------------------------------------
    def _on_command(self, rec: CommandInt | CommandLong, now_s: float) -> None:
        self.counters.commands_for_us += 1
        src = rec.src
        if rec.command != mavlink.MAV_CMD_DO_REPOSITION:
            if rec.target_component != BROADCAST:
                # To all components, the command is the autopilot's to answer: an UNSUPPORTED from us beside
                # its ACCEPTED would read as a refusal.
                self.outbox.ack(rec.command, mavlink.MAV_RESULT_UNSUPPORTED, src.system, src.component)
            return
        if isinstance(rec, CommandLong):
            self.outbox.ack(rec.command, mavlink.MAV_RESULT_COMMAND_INT_ONLY, src.system, src.component)
            return
        try:
            route = local_goal_from_reposition(
                frame=rec.frame,
                x=rec.x,
                y=rec.y,
                z=rec.z,
                reference=self.global_ref,
                source=f"mavlink:{src.system}/{src.component}",
            )
        except RepositionError as err:
            self.counters.bad_goals += 1
            self.outbox.ack(rec.command, err.result, src.system, src.component)
            log.info("goal.rejected", extra={"source": "mavlink", "error": str(err)})
            return
        accepted = self._set_route(route, now_s)
        result = mavlink.MAV_RESULT_ACCEPTED if accepted else mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        self.outbox.ack(rec.command, result, src.system, src.component)

    def home_amsl_m(self) -> float | None:
        """Home altitude AMSL (GLOBAL_POSITION_INT alt - relative_alt) [m], None until heard."""
        ref = self.global_ref
        return None if ref is None else ref.alt_amsl_m - ref.alt_rel_m


_AUTOPILOT: dict[type[Any], Callable[[AutopilotHandlers, Any, float], None]] = {
    Heartbeat: AutopilotHandlers._on_heartbeat,
    LocalPositionNed: AutopilotHandlers._on_local_position,
    Attitude: AutopilotHandlers._on_attitude,
    GlobalPositionInt: AutopilotHandlers._on_global_position,
    ObstacleDistance: AutopilotHandlers._on_obstacle_distance,
    DistanceSensor: AutopilotHandlers._on_distance_sensor,
    ObstacleDistance3d: AutopilotHandlers._on_obstacle_distance_3d,
    Odometry: AutopilotHandlers._on_odometry,
    EkfStatusReport: AutopilotHandlers._on_ekf_status,
    CommandAck: AutopilotHandlers._on_command_ack,
    PositionTargetLocalNed: AutopilotHandlers._on_position_target_local,
    PositionTargetGlobalInt: AutopilotHandlers._on_position_target_global,
    MissionCount: AutopilotHandlers._on_fence,
    MissionCurrent: AutopilotHandlers._on_fence,
    MissionItemInt: AutopilotHandlers._on_fence,
    MissionAck: AutopilotHandlers._on_fence,
    ParamValue: AutopilotHandlers._on_fence,
    HomePosition: AutopilotHandlers._on_fence,
    SysStatus: AutopilotHandlers._on_fence,
}
"""One handler per record type from the autopilot (commands from it are not for us: ignored)."""


def _message_name(msg_id: int) -> str:
    """A message's name from pymavlink's dialect (its id where the dialect has none)."""
    entry = mavlink.mavlink_map.get(msg_id)
    return str(entry.msgname) if entry is not None else str(msg_id)
