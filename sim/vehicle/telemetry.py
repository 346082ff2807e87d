"""Telemetry: one builder per message (``BUILDERS``, keyed by message id) and a per-link stream scheduler.

Like ArduPilot's GCS_MAVLINK (``GCS_Common.cpp``: ``try_send_message`` per message id, intervals per link),
every link has its own interval per message; SET_MESSAGE_INTERVAL changes one link's, 0 restores the default
and a negative interval stops the stream. A builder returns None when the message has nothing to say now
(POSITION_TARGET_LOCAL_NED outside GUIDED / OFFBOARD).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import ACC_IGNORE, VEL_IGNORE, YAW_ALL_IGNORE, Autopilot
from sim.vehicle.config import DEFAULT_RATES_HZ
from sim.vehicle.dynamics import TargetKind
from sim.vehicle.fenceswitch import geofence_flags
from sim.vehicle.geo import ne_to_latlon
from sim.vehicle.missionwire import MissionCurrentWithIds, plan_id
from sim.vehicle.profiles import Behaviour

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["BUILDERS", "DATA_STREAMS", "STREAM_IDS", "TelemetryScheduler", "as_list", "build"]

Builder = Callable[["VehicleEngine"], Any]

STREAM_IDS: dict[str, int] = {name: getattr(mavlink, f"MAVLINK_MSG_ID_{name}") for name in DEFAULT_RATES_HZ}

SENSORS_PRESENT = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS
)
LOAD_PERMILLE = 150
BATTERY_MV = 12600
BATTERY_CA = 500
BATTERY_PCT = 90
CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
)
SIM_UID = 0x53494D0000000001  # "SIM" + 1
GPS_EPH_CM = 80  # GPS_RAW_INT: HDOP 0.8 ...
GPS_EPV_CM = 120  # ... VDOP 1.2
GPS_SATELLITES = 12
EKF_VARIANCE = 0.05  # EKF_STATUS_REPORT test ratios: well below the 0.8 failsafe threshold (FS_EKF_THRESH)
_GUIDED_FLAG_BEHAVIOURS = frozenset({Behaviour.GUIDED, Behaviour.RTL, Behaviour.LAND, Behaviour.TAKEOFF})


def base_mode(v: VehicleEngine) -> int:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    if v.behaviour() in _GUIDED_FLAG_BEHAVIOURS:
        base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
    if v.armed:
        base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    return int(base)


def system_status(v: VehicleEngine) -> int:
    if v.crashed:
        return int(mavlink.MAV_STATE_EMERGENCY)
    if v.failsafe:
        return int(mavlink.MAV_STATE_CRITICAL)
    return int(mavlink.MAV_STATE_ACTIVE if v.armed else mavlink.MAV_STATE_STANDBY)


def _heartbeat(v: VehicleEngine) -> Any:
    return v.mav.heartbeat_encode(
        mavlink.MAV_TYPE_QUADROTOR, v.profile_rules.mav_autopilot, base_mode(v), v.custom_mode, system_status(v)
    )


def sensor_flags(v: VehicleEngine) -> tuple[int, int, int]:
    """SYS_STATUS onboard_control_sensors_(present, enabled, health), as ArduPilot's GCS.cpp
    update_sensor_status_flags: the geofence bit is healthy unless the fence is breached (sim.vehicle.fencebreach),
    also when no fence is present (MAVProxy reports "fence breach" when the bit drops), present when one
    is configured and enabled when it is switched on (``fenceswitch.geofence_flags``); PREARM_CHECK is present
    and enabled, and healthy when armed or when arming would pass."""
    present = enabled = int(SENSORS_PRESENT)
    health = present if not v.crashed else 0
    ardupilot_breach = v.profile is Autopilot.ARDUPILOT and v.fence.guard.breached  # AC_Fence sys_status_failed
    health |= 0 if ardupilot_breach else mavlink.MAV_SYS_STATUS_GEOFENCE
    rules = v.profile_rules
    if rules.reports_prearm_check:
        present |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        enabled |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if v.armed or (not v.crashed and rules.arm_refusal(v, force=False) is None):
            health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
    prx_present, prx_enabled, prx_health = v.proximity.sensor_flags(v.t_s)  # none unless PRX1_TYPE at boot
    if v.profile is Autopilot.ARDUPILOT:  # the fence present, and switched on (sim.vehicle.fenceswitch)
        on = v.fence.switch.follow(v.params["FENCE_ENABLE"] == 1.0)
        fence_present, fence_enabled = geofence_flags(
            int(v.params["FENCE_TYPE"]), bool(v.fence.items), on, int(v.params["FENCE_ACTION"])
        )
        present, enabled = present | fence_present, enabled | fence_enabled
    return present | prx_present, enabled | prx_enabled, health | prx_health


def _sys_status(v: VehicleEngine) -> Any:
    present, enabled, health = sensor_flags(v)
    return v.mav.sys_status_encode(
        present, enabled, health, LOAD_PERMILLE, BATTERY_MV, BATTERY_CA, BATTERY_PCT, 0, 0, 0, 0, 0, 0
    )


def _local_position_ned(v: VehicleEngine) -> Any:
    if not v.startup.origin_set:
        return None  # GCS_Common.cpp send_local_position: no position relative to an origin yet
    p, vel = v.estimator.reported(v.state.pos_ned_m), v.state.vel_ned_m_s
    return v.mav.local_position_ned_encode(
        v.time_boot_ms, float(p[0]), float(p[1]), float(p[2]), float(vel[0]), float(vel[1]), float(vel[2])
    )


def _odometry(v: VehicleEngine) -> Any:
    """PX4's ODOMETRY from EKF2 (streams/ODOMETRY.hpp): LOCAL_NED pose, the estimator's reset counter."""
    if not v.startup.origin_set:
        return None
    p, vel = v.estimator.reported(v.state.pos_ned_m), v.state.vel_ned_m_s
    half = 0.5 * v.state.yaw_rad
    cov = [math.nan] * 21
    return v.mav.odometry_encode(
        v.time_boot_ms * 1000,
        mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.MAV_FRAME_BODY_FRD,
        *(float(x) for x in p),
        [math.cos(half), 0.0, 0.0, math.sin(half)],
        *(float(x) for x in vel),  # NED here; PX4 sends them in its velocity frame
        0.0,
        0.0,
        0.0,
        cov,
        cov,
        reset_counter=v.estimator.reset_counter,
        estimator_type=mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT,
    )


def _global_position_int(v: VehicleEngine) -> Any:
    st = v.state
    if not v.startup.origin_set:
        # GCS_Common.cpp send_global_position_int ignores get_location's failure: the stale (zero) location
        return v.mav.global_position_int_encode(v.time_boot_ms, 0, 0, 0, 0, 0, 0, 0, 0)
    p = v.estimator.reported(st.pos_ned_m)  # the estimate: the global position jumps with the local one
    lat, lon = ne_to_latlon(v.cfg.home, float(p[0]), float(p[1]))
    vel = st.vel_ned_m_s
    hdg = round(math.degrees(st.yaw_rad) * 100.0) % 36000
    return v.mav.global_position_int_encode(
        v.time_boot_ms,
        round(lat * 1e7),
        round(lon * 1e7),
        round((v.cfg.home.alt_amsl_m + st.alt_m) * 1000.0),
        round(st.alt_m * 1000.0),
        round(vel[0] * 100.0),
        round(vel[1] * 100.0),
        round(vel[2] * 100.0),
        hdg,
    )


def _gps_raw_int(v: VehicleEngine) -> Any:
    """A healthy 3D fix at the vehicle (MAVSDK's health.is_global_position_ok falls back to fix >= 3 and >= 8
    satellites when SYS_STATUS has no GPS bit)."""
    st = v.state
    p = v.estimator.reported(st.pos_ned_m)  # the estimate: the global position jumps with the local one
    lat, lon = ne_to_latlon(v.cfg.home, float(p[0]), float(p[1]))
    vel = st.vel_ned_m_s
    speed_cm_s = round(float(np.hypot(vel[0], vel[1])) * 100.0)
    cog_cdeg = round(math.degrees(math.atan2(vel[1], vel[0])) * 100.0) % 36000
    return v.mav.gps_raw_int_encode(
        int(v.boot_s * 1e6),
        mavlink.GPS_FIX_TYPE_3D_FIX,
        round(lat * 1e7),
        round(lon * 1e7),
        round((v.cfg.home.alt_amsl_m + st.alt_m) * 1000.0),
        GPS_EPH_CM,
        GPS_EPV_CM,
        speed_cm_s,
        cog_cdeg,
        GPS_SATELLITES,
    )


def _attitude(v: VehicleEngine) -> Any:
    """ATTITUDE's rates are body (gyro) rates, as ArduPilot (``GCS_Common.cpp`` ``send_attitude``:
    ``ahrs.get_gyro()``) and PX4 (``vehicle_angular_velocity``) send them: the heading rate psi_dot, with roll
    and pitch held, is p = -sin(theta) psi_dot, q = sin(phi) cos(theta) psi_dot, r = cos(phi) cos(theta) psi_dot."""
    roll, pitch = v.state.attitude_rad()
    psi_dot = v.state.yaw_rate_rad_s
    p = -math.sin(pitch) * psi_dot
    q = math.sin(roll) * math.cos(pitch) * psi_dot
    r = math.cos(roll) * math.cos(pitch) * psi_dot
    return v.mav.attitude_encode(v.time_boot_ms, roll, pitch, v.state.yaw_rad, p, q, r)


def landed_state(v: VehicleEngine) -> int:
    behaviour = v.behaviour()
    if v.state.on_ground:
        return int(mavlink.MAV_LANDED_STATE_ON_GROUND)
    if behaviour is Behaviour.LAND or (behaviour is Behaviour.RTL and v.rtl_phase >= 2):
        return int(mavlink.MAV_LANDED_STATE_LANDING)
    if v.takeoff_alt_m is not None:
        return int(mavlink.MAV_LANDED_STATE_TAKEOFF)
    return int(mavlink.MAV_LANDED_STATE_IN_AIR)


def _extended_sys_state(v: VehicleEngine) -> Any:
    return v.mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, landed_state(v))


def _home_position(v: VehicleEngine) -> Any:
    if not v.startup.origin_set:
        return None  # GCS_Common.cpp send_home_position: home not set yet
    h = v.cfg.home
    lat, lon, alt = round(h.lat_deg * 1e7), round(h.lon_deg * 1e7), round(h.alt_amsl_m * 1000.0)
    q = [1.0, 0.0, 0.0, 0.0]
    return v.mav.home_position_encode(lat, lon, alt, 0.0, 0.0, 0.0, q, 0.0, 0.0, 0.0, time_usec=int(v.boot_s * 1e6))


def _position_target_local_ned(v: VehicleEngine) -> Any:
    sp = v.guided.sp
    if sp is None or v.behaviour() is not Behaviour.GUIDED:
        return None
    z3 = (0.0, 0.0, 0.0)
    pos = v.estimator.reported(sp.pos) if sp.pos is not None else z3  # the held target in the estimate's frame
    vel = sp.vel if sp.vel is not None else z3
    acc = sp.acc if sp.acc is not None else z3
    rules = v.profile_rules
    echo_yaw = rules.echoes_target_yaw
    return v.mav.position_target_local_ned_encode(
        v.time_boot_ms,
        mavlink.MAV_FRAME_LOCAL_NED,
        rules.echo_type_mask(sp),
        *(float(x) for x in pos),
        *(float(x) for x in vel),
        *(float(x) for x in acc),
        float(sp.yaw or 0.0) if echo_yaw else 0.0,
        float(sp.yaw_rate or 0.0) if echo_yaw else 0.0,
    )


def _ekf_status_report(v: VehicleEngine) -> Any:
    """The EKF's solution flags (sim/vehicle/startup.py); variances small and constant."""
    return v.mav.ekf_status_report_encode(v.startup.flags, EKF_VARIANCE, EKF_VARIANCE, EKF_VARIANCE, EKF_VARIANCE, 0.0)


def _position_target_global_int(v: VehicleEngine) -> Any:
    """ArduCopter reports a guided target as a location only in its position-only submodes (WP, Pos:
    ``ModeGuided::get_wp``), not for position+velocity targets (a companion's stream), in MAV_FRAME_GLOBAL with
    the altitude AMSL (``GCS_MAVLINK_Copter::send_position_target_global_int``)."""
    sp = v.guided.sp
    if v.profile_rules.autopilot is not Autopilot.ARDUPILOT or sp is None or v.behaviour() is not Behaviour.GUIDED:
        return None
    if sp.kind is not TargetKind.POSITION or sp.pos is None or sp.vel is not None or sp.acc is not None:
        return None
    home = v.cfg.home
    lat, lon = ne_to_latlon(home, float(sp.pos[0]), float(sp.pos[1]))
    return v.mav.position_target_global_int_encode(
        v.time_boot_ms,
        mavlink.MAV_FRAME_GLOBAL,
        int(VEL_IGNORE | ACC_IGNORE | YAW_ALL_IGNORE),
        round(lat * 1e7),
        round(lon * 1e7),
        home.alt_amsl_m - float(sp.pos[2]),
        *([0.0] * 8),
    )


def _vfr_hud(v: VehicleEngine) -> Any:
    vel = v.state.vel_ned_m_s
    gs = float(np.hypot(vel[0], vel[1]))
    hdg = round(math.degrees(v.state.yaw_rad)) % 360
    throttle_pct = 50 if v.armed else 0
    return v.mav.vfr_hud_encode(gs, gs, hdg, throttle_pct, v.state.alt_m, -float(vel[2]))


def _system_time(v: VehicleEngine) -> Any:
    return v.mav.system_time_encode(0, v.time_boot_ms)


def _distance_sensor(v: VehicleEngine) -> list[Any]:
    """The proximity library's 8 faces (sim/vehicle/proximity.py); nothing unless its status is Good."""
    return v.proximity.distance_sensor_msgs(v.mav, v.t_s, v.time_boot_ms)


def _mission_current(v: VehicleEngine) -> Any:
    """No mission here; PX4 adds its fence plan's id (``mavlink_mission.cpp`` ``send_mission_current``, 1 Hz on
    every link), ArduPilot sends none (``GCS_Common.cpp`` ``send_mission_current``: seq, total, state, mode)."""
    if v.profile is Autopilot.PX4:
        return MissionCurrentWithIds(0, 0xFFFF, mavlink.MISSION_STATE_NO_MISSION, 0, plan_id(v.fence.items))
    return v.mav.mission_current_encode(0, 0, mavlink.MISSION_STATE_NO_MISSION, 0)


def _autopilot_version(v: VehicleEngine) -> Any:
    version = v.profile_rules.flight_sw_version
    return v.mav.autopilot_version_encode(CAPABILITIES, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, SIM_UID)


BUILDERS: dict[int, Builder] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: _heartbeat,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: _sys_status,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _local_position_ned,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position_int,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: _attitude,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: _extended_sys_state,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: _home_position,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: _position_target_local_ned,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT: _position_target_global_int,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: _vfr_hud,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: _system_time,
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: _autopilot_version,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: _gps_raw_int,
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: _distance_sensor,
    mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT: _ekf_status_report,
    mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: _mission_current,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: _odometry,
}

# REQUEST_DATA_STREAM: the messages of each stream that this vehicle builds (ArduCopter GCS_MAVLink_Copter.cpp
# STREAM_*_msgs: EXTENDED_STATUS has SYS_STATUS and GPS_RAW, POSITION has LOCATION and LOCAL_POSITION, EXTRA1
# ATTITUDE, EXTRA2 VFR_HUD, EXTRA3 SYSTEM_TIME and EKF_STATUS_REPORT). MAV_DATA_STREAM_ALL sets all of them.
DATA_STREAMS: dict[int, tuple[int, ...]] = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: (mavlink.MAVLINK_MSG_ID_SYS_STATUS, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT),
    mavlink.MAV_DATA_STREAM_POSITION: (
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    ),
    mavlink.MAV_DATA_STREAM_EXTRA1: (mavlink.MAVLINK_MSG_ID_ATTITUDE,),
    mavlink.MAV_DATA_STREAM_EXTRA2: (mavlink.MAVLINK_MSG_ID_VFR_HUD,),
    mavlink.MAV_DATA_STREAM_EXTRA3: (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT),
}

SR_STREAMS = {  # SRn_<group> parameter -> its stream (GCS_MAVLink_Copter.cpp stream-rate parameters)
    "EXT_STAT": mavlink.MAV_DATA_STREAM_EXTENDED_STATUS,
    "POSITION": mavlink.MAV_DATA_STREAM_POSITION,
    "EXTRA1": mavlink.MAV_DATA_STREAM_EXTRA1,
    "EXTRA2": mavlink.MAV_DATA_STREAM_EXTRA2,
    "EXTRA3": mavlink.MAV_DATA_STREAM_EXTRA3,
}


def as_list(built: Any) -> list[Any]:
    """A builder's result as a list of messages (a builder returns one, None, or a list: DISTANCE_SENSOR)."""
    if built is None:
        return []
    return built if isinstance(built, list) else [built]


def build(v: VehicleEngine, msg_id: int) -> Any:
    """The message ``msg_id`` as the vehicle would send it now; None if unknown or nothing to send."""
    builder = BUILDERS.get(msg_id)
    return None if builder is None else builder(v)


@dataclass(slots=True)
class Stream:
    interval_s: float  # 0 = off
    next_t: float


class TelemetryScheduler:
    """Which message is due on which link; each link has its own intervals (SET_MESSAGE_INTERVAL)."""

    def __init__(
        self, n_links: int, rates_hz: Mapping[str, float], *, min_interval_s: float, unasked: bool = True
    ) -> None:
        rates = {**DEFAULT_RATES_HZ, **rates_hz}
        self.default_intervals = {STREAM_IDS[name]: (1.0 / r if r > 0 else 0.0) for name, r in rates.items()}
        self.min_interval_s = min_interval_s
        # ``unasked`` False: only HEARTBEAT until a stream is requested (HEARTBEAT is not a stream in ArduPilot:
        # GCS_Common.cpp sends it at 1 Hz on every link regardless of the stream rates)
        boot = {
            msg_id: (iv if unasked or msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT else 0.0)
            for msg_id, iv in self.default_intervals.items()
        }
        self.streams: list[dict[int, Stream]] = [
            {msg_id: Stream(iv, 0.0) for msg_id, iv in boot.items()} for _ in range(n_links)
        ]

    def streamable(self, msg_id: int) -> bool:
        return msg_id in self.default_intervals

    def tick(self, v: VehicleEngine, emit: Callable[[int, Any], None]) -> None:
        """Send every message due at ``v.t_s``; a message due on several links is built once."""
        t_s = v.t_s
        cache: dict[int, Any] = {}
        for link, streams in enumerate(self.streams):
            for msg_id, st in streams.items():
                if st.interval_s <= 0 or t_s < st.next_t - 1e-9:
                    continue
                st.next_t = max(st.next_t + st.interval_s, t_s + 0.5 * st.interval_s)
                if msg_id not in cache:
                    cache[msg_id] = build(v, msg_id)
                for msg in as_list(cache[msg_id]):
                    emit(link, msg)

    def set_interval(self, link: int, msg_id: int, interval_us: float, t_s: float) -> bool:
        """SET_MESSAGE_INTERVAL: 0 = default, < 0 = off; False for a message this vehicle does not stream."""
        if msg_id not in self.default_intervals:
            return False
        stream = self.streams[link][msg_id]
        if interval_us == 0:
            stream.interval_s = self.default_intervals[msg_id]
        elif interval_us < 0:
            stream.interval_s = 0.0
        else:
            stream.interval_s = max(interval_us * 1e-6, self.min_interval_s)
        stream.next_t = t_s
        return True

    def reset(self, t_s: float) -> None:
        """After a reboot: every link back to the default intervals (SET_MESSAGE_INTERVAL is not stored)."""
        for streams in self.streams:
            for msg_id, st in streams.items():
                st.interval_s, st.next_t = self.default_intervals[msg_id], t_s

    def set_data_stream(self, link: int, stream_id: int, rate_hz: float, t_s: float) -> None:
        """REQUEST_DATA_STREAM: every message of the stream (all streams for MAV_DATA_STREAM_ALL) at ``rate_hz``
        on this link, 0 = off (GCS_Common.cpp handle_request_data_stream sets the SRn_ stream rate)."""
        if stream_id == mavlink.MAV_DATA_STREAM_ALL:
            ids = tuple(i for group in DATA_STREAMS.values() for i in group)
        else:
            ids = DATA_STREAMS.get(stream_id, ())
        for msg_id in ids:
            self.set_interval(link, msg_id, 1e6 / rate_hz if rate_hz > 0 else -1.0, t_s)

    def boot_stream_rates(self, params: Mapping[str, float]) -> None:
        """SRn_<group> parameters set at boot: stream that group on link n at that rate (0 = as before)."""
        for name, rate_hz in params.items():
            link, _, group = name.removeprefix("SR").partition("_")
            stream = SR_STREAMS.get(group)
            if stream is not None and link.isdigit() and int(link) < len(self.streams) and rate_hz > 0:
                self.set_data_stream(int(link), stream, rate_hz, 0.0)

    def interval_us(self, link: int, msg_id: int) -> int:
        """GET_MESSAGE_INTERVAL's answer: the interval [us], -1 = off, 0 = not a stream of this vehicle."""
        if msg_id not in self.default_intervals:
            return 0
        iv = self.streams[link][msg_id].interval_s
        return round(iv * 1e6) if iv > 0 else -1
