"""The autopilot handlers: decoded MAVLink records in, to the part that owns what they carry.

Messages are accepted only from the configured autopilot (sysid/compid), one handler per record type
(``_AUTOPILOT``); the one exception is COMMAND_INT / COMMAND_LONG addressed to our component from a configured
ground-station sysid (DO_REPOSITION). Everything else is counted (``foreign_messages``) and dropped.

Owns what the autopilot says about itself: its mode and arming (HEARTBEAT), whether it has been heard, and the
global reference (GLOBAL_POSITION_INT) that places global goals and the PX4 takeoff altitude.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot, CopterMode, Px4MainMode, Px4Mode
from apf_companion.goal import GlobalReference, RepositionError, Route, local_goal_from_reposition
from apf_companion.links.messages import (
    Attitude,
    CommandInt,
    CommandLong,
    DistanceSensor,
    GlobalPositionInt,
    Heartbeat,
    LocalPositionNed,
    ObstacleDistance,
    ObstacleDistance3d,
    Odometry,
    Record,
    Source,
)
from apf_companion.navigator import Navigator
from apf_companion.outbox import Outbox
from apf_companion.perception import PerceptionFrontEnd
from apf_companion.reporter import ServiceCounters

__all__ = ["AutopilotHandlers", "HandlerParams", "mode_is_ours"]

log = logging.getLogger(__name__)

NOT_A_VEHICLE = frozenset({mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GCS})  # their HEARTBEATs
REBOOTING = frozenset({mavlink.MAV_STATE_UNINIT, mavlink.MAV_STATE_BOOT})  # HEARTBEAT.system_status
DEG_E7 = 1e-7
MM = 1e-3


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
    fly_config_goal_after_restart: bool = False  # [goal] fly_after_restart


class AutopilotHandlers:
    """Routes decoded records (see the module docstring).

    Args:
        set_route: Starts a goal (the service's; returns whether the navigator accepted it).
        on_pose: Called when the navigator accepted a new pose (it triggers a cycle).
        route_at_start: Flown once the autopilot is first heard.
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
        on_pose: Callable[[], None],
        route_at_start: Route | None,
    ) -> None:
        self.params = params
        self.perception = perception
        self.navigator = navigator
        self.outbox = outbox
        self.counters = counters
        self._set_route = set_route
        self._on_pose = on_pose
        self._route_at_start = route_at_start
        self.heard = False
        self.custom_mode: int | None = None
        self.base_mode = 0
        self.global_ref: GlobalReference | None = None

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode_ok(self) -> bool:
        """The autopilot's latest mode is ours (GUIDED / OFFBOARD); False before its first HEARTBEAT."""
        return self.custom_mode is not None and mode_is_ours(self.params.profile, self.custom_mode)

    def handle(self, rec: Record, now_s: float) -> None:
        if rec.src == self.params.autopilot:
            handler = _AUTOPILOT.get(type(rec))
            if handler is not None:
                handler(self, rec, now_s)
        elif isinstance(rec, CommandInt | CommandLong) and self._for_us(rec):
            self._on_command(rec, now_s)
        else:
            self.counters.foreign_messages += 1

    def undecoded(self, consumed: bool, src: Source | None) -> None:
        """A message without a record: malformed if its type is consumed; else foreign unless from the autopilot."""
        if consumed:
            self.counters.undecodable_messages += 1
        elif src != self.params.autopilot:
            self.counters.foreign_messages += 1

    def _for_us(self, rec: CommandInt | CommandLong) -> bool:
        p = self.params
        return (
            rec.src.system in p.gcs_sysids
            and rec.target_system == p.autopilot.system
            and rec.target_component == p.component_id
        )

    # ---- from the autopilot ------------------------------------------------------------------------------------
    def _on_heartbeat(self, rec: Heartbeat, now_s: float) -> None:
        if rec.type in NOT_A_VEHICLE:
            return
        at_start = not self.heard  # this process's first HEARTBEAT
        first = at_start or not self.navigator.link_alive(now_s)
        if (self.heard and first) or rec.system_status in REBOOTING:
            self.perception.gate.note_reboot()  # boot evidence: a pose may start a new time base
        self.heard = True
        self.custom_mode = rec.custom_mode
        self.base_mode = rec.base_mode
        self.navigator.autopilot_heartbeat(now_s, mode_ok=self.params.dry_run or self.mode_ok)
        if first:
            self.outbox.request_streams(self.params.telemetry_rate_hz)
            route, self._route_at_start = self._route_at_start, None
            restarted = self._restarted_mid_flight(route) if at_start else None
            if restarted is not None:
                self.navigator.recovery.restart_hold(now_s, restarted)
            elif route is not None:
                self._set_route(route, now_s)

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
        pose = self.perception.on_local_position(rec.time_boot_ms, (rec.x, rec.y, rec.z), now_s)
        reset = self.perception.take_reset()
        if reset is not None:
            self.navigator.recovery.position_reset(now_s, reset)
        self.navigator.recovery.pose_confirmed = self.perception.gate.confirmed
        if pose is not None and self.navigator.update_pose(pose):
            self._on_pose()

    def _on_odometry(self, rec: Odometry, now_s: float) -> None:
        self.perception.gate.note_reset_counter(rec.reset_counter)  # estimator reset evidence for the pose gate

    def _on_attitude(self, rec: Attitude, now_s: float) -> None:
        self.perception.on_attitude(rec.yaw)

    def _on_global_position(self, rec: GlobalPositionInt, now_s: float) -> None:
        pose = self.navigator.pose
        if pose is None:
            return
        lat, lon = rec.lat * DEG_E7, rec.lon * DEG_E7
        alt, rel = rec.alt * MM, rec.relative_alt * MM
        if not all(math.isfinite(v) for v in (lat, lon, alt, rel)) or (rec.lat == 0 and rec.lon == 0):
            return
        p = pose.pos_ned_m
        self.global_ref = GlobalReference(
            lat_deg=lat, lon_deg=lon, alt_amsl_m=alt, alt_rel_m=rel, pos_ned_m=(p[0], p[1], p[2])
        )

    def _on_obstacle_distance(self, rec: ObstacleDistance, now_s: float) -> None:
        if self.params.mavlink_ranges:
            self.perception.on_obstacle_distance(rec, now_s)

    def _on_distance_sensor(self, rec: DistanceSensor, now_s: float) -> None:
        if self.params.mavlink_ranges:
            self.perception.on_distance_sensor(rec, now_s)

    def _on_obstacle_distance_3d(self, rec: ObstacleDistance3d, now_s: float) -> None:
        if self.params.mavlink_ranges:
            self.perception.on_obstacle_distance_3d(rec, now_s)

    # ---- commands for us ---------------------------------------------------------------------------------------
    def _on_command(self, rec: CommandInt | CommandLong, now_s: float) -> None:
        self.counters.commands_for_us += 1
        src = rec.src
        if rec.command != mavlink.MAV_CMD_DO_REPOSITION:
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
}
"""One handler per record type from the autopilot (commands from it are not for us: ignored)."""
