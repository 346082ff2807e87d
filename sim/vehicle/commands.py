"""COMMAND_LONG / COMMAND_INT: one handler per MAV_CMD (``COMMANDS``), answered with a COMMAND_ACK.

A handler returns the MAV_RESULT to ACK, or None when it has already answered (ACK followed by the message
asked for). Unknown commands get UNSUPPORTED (ArduPilot ``GCS_Common.cpp`` handle_command_long_packet). Where
ArduCopter and PX4 differ the handler asks the vehicle's profile (``sim.vehicle.profiles``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from sim.vehicle.geo import GLOBAL_FRAMES, down_from_alt, latlon_to_ne
from sim.vehicle.profiles import param_int
from sim.vehicle.reboot import handle_reboot
from sim.vehicle.telemetry import as_list, build

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["COMMANDS", "Command", "handle_command"]

FORCE_ARM_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2: arm/disarm even if checks fail (common.xml)
UNSUPPORTED_CMD_LONG_ONLY = frozenset({mavlink.MAV_CMD_DO_REPOSITION})  # needs COMMAND_INT (a frame)
ACCEPTED = int(mavlink.MAV_RESULT_ACCEPTED)


@dataclass(frozen=True, slots=True)
class Command:
    """A decoded COMMAND_LONG or COMMAND_INT (``frame`` None for COMMAND_LONG); x and y of COMMAND_INT are
    params 5 and 6 as received (degE7 for global frames)."""

    msg: Any
    link: int
    command: int
    p: tuple[float, ...]
    frame: int | None


CommandHandler = Callable[["VehicleEngine", Command], int | None]


def handle_command(v: VehicleEngine, c: Command) -> None:
    fn = COMMANDS.get(c.command)
    result = mavlink.MAV_RESULT_UNSUPPORTED if fn is None else fn(v, c)
    if result is not None:
        v.ack(c.link, c.msg, c.command, result)


# -- arming
def _arm(v: VehicleEngine, c: Command) -> int:
    force = param_int(c.p[1]) == FORCE_ARM_MAGIC
    if not c.p[0] >= 0.5:
        return _disarm(v, force=force)
    if v.armed:
        return ACCEPTED
    refusal = "Arm: vehicle crashed" if v.crashed else v.profile_rules.arm_refusal(v, force=force)
    if refusal is not None:
        v.statustext(mavlink.MAV_SEVERITY_CRITICAL, refusal)
        return v.profile_rules.fail_result
    v.armed = True
    v.armed_t_s = v.t_s
    v.landed_since_s = v.t_s
    v.statustext(mavlink.MAV_SEVERITY_INFO, v.profile_rules.texts.armed)
    return ACCEPTED


def _disarm(v: VehicleEngine, *, force: bool) -> int:
    if not v.armed:
        return ACCEPTED
    if not v.state.on_ground and not force:
        v.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Disarm refused: vehicle in the air")
        return v.profile_rules.fail_result
    v.disarm(v.profile_rules.texts.disarmed)
    return ACCEPTED


# -- modes
def _set_mode(v: VehicleEngine, c: Command) -> int:
    if not param_int(c.p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return v.profile_rules.no_custom_mode_result
    return v.profile_rules.request_mode(v, v.profile_rules.mode_from_command(c.p))


# -- takeoff / land / rtl / reposition
def _takeoff(v: VehicleEngine, c: Command) -> int:
    if v.crashed:
        return v.profile_rules.fail_result
    return v.profile_rules.takeoff(v, c.p)


def _land(v: VehicleEngine, c: Command) -> int:
    if v.crashed:
        return v.profile_rules.fail_result
    v.set_mode(v.profile_rules.land_mode, "land command")
    return ACCEPTED


def _rtl(v: VehicleEngine, c: Command) -> int:
    if v.crashed:
        return v.profile_rules.fail_result
    v.set_mode(v.profile_rules.rtl_mode, "rtl command")
    return ACCEPTED


def _reposition(v: VehicleEngine, c: Command) -> int:
    if c.frame is None:
        return int(mavlink.MAV_RESULT_UNSUPPORTED)
    if c.frame not in GLOBAL_FRAMES or v.crashed or v.state.on_ground:
        return v.profile_rules.fail_result
    n, e = latlon_to_ne(v.cfg.home, c.p[4] * 1e-7, c.p[5] * 1e-7)
    target = np.array([n, e, down_from_alt(v.cfg.home, c.frame, c.p[6])])
    return v.profile_rules.reposition(v, c.p, target)


def _change_speed(v: VehicleEngine, c: Command) -> int:
    speed = c.p[1]
    if not speed > 0:
        return v.profile_rules.fail_result
    err = v.profile_rules.change_speed(v.params, speed)
    return int(mavlink.MAV_RESULT_ACCEPTED if err is None else mavlink.MAV_RESULT_DENIED)


# -- message requests
def _set_message_interval(v: VehicleEngine, c: Command) -> int:
    # an unknown message id: ArduPilot DENIED (GCS_Common.cpp set_message_interval, "No ap_message for mavlink
    # id"), PX4 FAILED (mavlink_receiver.cpp set_message_interval returns PX4_ERROR); NaN interval = default
    interval_us = c.p[1] if math.isfinite(c.p[1]) else 0.0
    ok = v.telemetry.set_interval(c.link, param_int(c.p[0], -1), interval_us, v.t_s)
    return ACCEPTED if ok else v.profile_rules.unknown_message_result


def _get_message_interval(v: VehicleEngine, c: Command) -> None:
    msg_id = param_int(c.p[0], -1)
    interval_us = v.telemetry.interval_us(c.link, msg_id)
    v.ack(c.link, c.msg, c.command, mavlink.MAV_RESULT_ACCEPTED)
    v.emit(c.link, v.mav.message_interval_encode(max(msg_id, 0), interval_us))


def _request_message(v: VehicleEngine, c: Command) -> int | None:
    msg_id = param_int(c.p[0], -1)
    out = as_list(build(v, msg_id)) if v.telemetry.streamable(msg_id) else []
    if not out:
        return int(mavlink.MAV_RESULT_FAILED)
    v.ack(c.link, c.msg, c.command, mavlink.MAV_RESULT_ACCEPTED)
    for msg in out:
        v.emit(c.link, msg)
    return None


def _condition_yaw(v: VehicleEngine, c: Command) -> int:
    return v.profile_rules.condition_yaw(v, c.p)


def _fence_enable(v: VehicleEngine, c: Command) -> int:
    """MAV_CMD_DO_FENCE_ENABLE: ArduPilot's run-time switch (``GCS_Fence.cpp``; sim.vehicle.fenceswitch)."""
    if v.profile is not Autopilot.ARDUPILOT:  # the PX4 profile keeps no such switch
        return int(mavlink.MAV_RESULT_UNSUPPORTED)
    return v.fence.switch.command(float(c.p[0]))


def _send_after_ack(msg_id: int) -> CommandHandler:
    """ACCEPTED and the message, or FAILED when there is nothing to send yet (no home before the EKF origin:
    GCS_Common.cpp ``handle_command_get_home_position`` returns MAV_RESULT_FAILED while ``!home_is_set()``)."""

    def handler(v: VehicleEngine, c: Command) -> int | None:
        out = as_list(build(v, msg_id))
        if not out:
            return int(mavlink.MAV_RESULT_FAILED)
        v.ack(c.link, c.msg, c.command, mavlink.MAV_RESULT_ACCEPTED)
        for msg in out:
            v.emit(c.link, msg)
        return None

    return handler


COMMANDS: dict[int, CommandHandler] = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: _arm,
    mavlink.MAV_CMD_DO_SET_MODE: _set_mode,
    mavlink.MAV_CMD_NAV_TAKEOFF: _takeoff,
    mavlink.MAV_CMD_NAV_LAND: _land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: _rtl,
    mavlink.MAV_CMD_DO_REPOSITION: _reposition,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: _change_speed,
    mavlink.MAV_CMD_CONDITION_YAW: _condition_yaw,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: _set_message_interval,
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: _get_message_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: _request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: _send_after_ack(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
    mavlink.MAV_CMD_GET_HOME_POSITION: _send_after_ack(mavlink.MAVLINK_MSG_ID_HOME_POSITION),
    mavlink.MAV_CMD_DO_FENCE_ENABLE: _fence_enable,
    mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: handle_reboot,
}
