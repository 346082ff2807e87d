"""Incoming MAVLink: one handler per message id (``HANDLERS``), as ArduPilot's ``GCS_MAVLINK::handle_message``.

Messages with target_system / target_component answer only when addressed to this vehicle (or broadcast).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.vehicle.commands import UNSUPPORTED_CMD_LONG_ONLY, Command, handle_command
from sim.vehicle.fence import FENCE_HANDLERS
from sim.vehicle.geo import GLOBAL_FRAMES, down_from_alt, latlon_to_ne
from sim.vehicle.guided import decode_setpoint
from sim.vehicle.param_protocol import PARAM_HANDLERS
from sim.world.model import FloatArray

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["COMPID", "HANDLERS", "SYSID", "handle_message"]

SYSID = 1
COMPID = 1

MessageHandler = Callable[["VehicleEngine", Any, int], None]


def handle_message(v: VehicleEngine, msg: Any, link: int) -> None:
    if v.profile_rules.drops_own_ids and (msg.get_srcSystem(), msg.get_srcComponent()) == (SYSID, COMPID):
        # MAVLink_routing.cpp check_and_forward: "loopback of our own messages" is not processed locally
        v.own_id_drops += 1
        return
    handler = HANDLERS.get(msg.get_msgId())
    if handler is not None:
        handler(v, msg, link)


def addressed_to_us(msg: Any) -> bool:
    ts = getattr(msg, "target_system", 0)
    tc = getattr(msg, "target_component", 0)
    return ts in (0, SYSID) and tc in (0, COMPID)


def _for_us(fn: MessageHandler) -> MessageHandler:
    def handler(v: VehicleEngine, msg: Any, link: int) -> None:
        if addressed_to_us(msg):
            fn(v, msg, link)

    return handler


# -- commands and modes
def _on_command_long(v: VehicleEngine, msg: Any, link: int) -> None:
    p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
    if msg.command in UNSUPPORTED_CMD_LONG_ONLY:
        v.ack(link, msg, msg.command, mavlink.MAV_RESULT_UNSUPPORTED)
        return
    handle_command(v, Command(msg, link, msg.command, p, None))


def _on_command_int(v: VehicleEngine, msg: Any, link: int) -> None:
    p = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
    handle_command(v, Command(msg, link, msg.command, p, msg.frame))


def _on_set_mode(v: VehicleEngine, msg: Any, link: int) -> None:
    if msg.target_system not in (0, SYSID):
        return
    rules = v.profile_rules
    if not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        result = rules.no_custom_mode_result
    else:
        result = rules.request_mode(v, int(msg.custom_mode))
    v.ack(link, msg, rules.set_mode_ack_command, result)


# -- setpoints
def _on_set_position_target_local_ned(v: VehicleEngine, msg: Any, link: int) -> None:
    _apply_setpoint(v, msg, msg.coordinate_frame, np.array([msg.x, msg.y, msg.z], dtype=np.float64))


def _on_set_position_target_global_int(v: VehicleEngine, msg: Any, link: int) -> None:
    frame = msg.coordinate_frame
    if frame not in GLOBAL_FRAMES:
        # ArduCopter: an unknown frame "is not valid so stop" (GCS_MAVLink_Copter.cpp); PX4 drops it
        if not v.profile_rules.invalid_setpoint(v):
            v.warn_once_per_s("frame", mavlink.MAV_SEVERITY_WARNING, f"Setpoint ignored: frame {frame} unsupported")
        return
    n, e = latlon_to_ne(v.cfg.home, msg.lat_int * 1e-7, msg.lon_int * 1e-7)
    down = down_from_alt(v.cfg.home, frame, msg.alt)
    _apply_setpoint(v, msg, mavlink.MAV_FRAME_LOCAL_NED, np.array([n, e, down], dtype=np.float64))


def _apply_setpoint(v: VehicleEngine, msg: Any, frame: int, pos_in: FloatArray) -> None:
    rules = v.profile_rules
    if frame == mavlink.MAV_FRAME_LOCAL_NED:
        pos_in = v.estimator.flown(pos_in)  # read in the estimate's frame (sim.vehicle.ekfreset)
    rule = rules.setpoint_rule(int(msg.type_mask), frame)
    if rule.kind is None:
        if not rules.invalid_setpoint(v) and rule.text:
            v.warn_once_per_s(rule.text, rule.severity, rule.text)
        return
    # proof of life: PX4 publishes offboard_control_mode for every valid setpoint, in any mode (mavlink_receiver.cpp)
    v.guided.received(v.t_s)
    if not rules.accepts_setpoint(v):
        return
    sp = decode_setpoint(
        msg,
        frame,
        pos_in,
        rule.kind,
        mask=rule.type_mask,
        t_s=v.t_s,
        pos_now_ned_m=v.state.pos_ned_m,
        yaw_now_rad=v.state.yaw_rad,
        body_yaw_relative=rules.body_yaw_relative,
    )
    if sp is None:
        v.warn_once_per_s("nan", mavlink.MAV_SEVERITY_WARNING, "Setpoint ignored: not finite")
        return
    v.guided.set(sp)
    rules.after_external_target(v)


# -- the rest
def _on_timesync(v: VehicleEngine, msg: Any, link: int) -> None:
    # A request has tc1 == 0: answer with our clock (simulated ns since boot) and echo ts1.
    if msg.tc1 == 0:
        v.emit(link, v.mav.timesync_encode(int(v.boot_s * 1e9), msg.ts1))


def _on_obstacle_distance(v: VehicleEngine, msg: Any, link: int) -> None:
    # GCS_Common.cpp handle_obstacle_distance -> AP_Proximity: from anyone (no target fields)
    v.proximity.on_obstacle_distance(msg, v.t_s)


def _on_request_data_stream(v: VehicleEngine, msg: Any, link: int) -> None:
    # GCS_Common.cpp handle_request_data_stream: start_stop 0 stops, 1 starts at req_message_rate [Hz], else ignored
    if msg.start_stop not in (0, 1):
        return
    rate_hz = float(msg.req_message_rate) if msg.start_stop == 1 else 0.0
    v.telemetry.set_data_stream(link, int(msg.req_stream_id), rate_hz, v.t_s)


HANDLERS: dict[int, MessageHandler] = {
    mavlink.MAVLINK_MSG_ID_COMMAND_LONG: _for_us(_on_command_long),
    mavlink.MAVLINK_MSG_ID_COMMAND_INT: _for_us(_on_command_int),
    mavlink.MAVLINK_MSG_ID_SET_MODE: _on_set_mode,
    mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED: _for_us(_on_set_position_target_local_ned),
    mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT: _for_us(_on_set_position_target_global_int),
    **{msg_id: _for_us(fn) for msg_id, fn in PARAM_HANDLERS.items()},
    **{msg_id: _for_us(fn) for msg_id, fn in FENCE_HANDLERS.items()},  # the fence; no mission, no rally points
    mavlink.MAVLINK_MSG_ID_REQUEST_DATA_STREAM: _for_us(_on_request_data_stream),
    mavlink.MAVLINK_MSG_ID_TIMESYNC: _on_timesync,
    mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE: _on_obstacle_distance,
}
