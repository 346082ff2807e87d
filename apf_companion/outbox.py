"""Everything the service sends to the autopilot, encoded with pymavlink's dialect constants.

Silent (nothing on the wire) in a dry run or without a link. ``time_boot_ms`` of outgoing messages counts from the
outbox's creation on the service clock.

Never raises on a value (docs/hardening.md, "never crash on data"): a float field that float32 cannot represent
(|v| > 3.4e38, which pymavlink's ``struct.pack`` refuses) is clamped in a report (NAMED_VALUE_FLOAT, counted in
``clamped_values``) and makes a setpoint or command unsendable (skipped, counted in ``unsendable``); any packing
or sending error is counted in ``send_errors`` and logged once per kind.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import PX4_OFFBOARD, Autopilot, CopterMode
from apf_companion.links import MavlinkLink
from apf_companion.setpoint import Setpoint, encode_setpoint

__all__ = ["FLOAT32_MAX", "STREAM_INTERVALS", "Outbox", "float32_ok"]

log = logging.getLogger(__name__)

FLOAT32_MAX = 3.4028234663852886e38  # MAVLink float fields are IEEE float32

STATUSTEXT_BYTES = 50  # one STATUSTEXT's text field
GLOBAL_POSITION_INTERVAL_US = 200_000.0  # GLOBAL_POSITION_INT at 5 Hz: only the takeoff and DO_REPOSITION use it
UINT32_MASK = 0xFFFFFFFF

STREAM_INTERVALS: tuple[int, ...] = (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE)
"""Messages requested at ``link.telemetry_rate_hz`` (SET_MESSAGE_INTERVAL) once the autopilot is heard."""


def float32_ok(values: Iterable[float]) -> bool:
    """Every value fits a MAVLink float field (finite or NaN, |v| <= float32 max; inf is left to the caller)."""
    return all(not (abs(v) > FLOAT32_MAX and math.isfinite(v)) for v in values)


def clamp_float32(value: float) -> float:
    """``value`` clamped into float32's finite range (NaN stays NaN)."""
    return value if math.isnan(value) else max(-FLOAT32_MAX, min(FLOAT32_MAX, value))


class Outbox:
    """The sending side of the autopilot link.

    Args:
        link: The MAVLink link, or None (nothing is sent).
        dry_run: Compute everything, send nothing.
        target_system, target_component: The autopilot's ids.
        now_s: The service clock.
    """

    def __init__(
        self,
        link: MavlinkLink | None,
        *,
        dry_run: bool,
        target_system: int,
        target_component: int,
        now_s: Callable[[], float],
    ) -> None:
        self.link = link
        self.dry_run = dry_run
        self.target = (target_system, target_component)
        self._now_s = now_s
        self._start_s = now_s()
        self.setpoints_sent = 0
        self.last_setpoint: Setpoint | None = None  # the newest one that went out
        self.statustexts_sent = 0
        self.clamped_values = 0  # report values clamped into float32's range
        self.unsendable = 0  # setpoints / commands with a value float32 cannot carry: not sent
        self.send_errors = 0  # packing or sending raised: counted, logged once per kind
        self._logged: set[str] = set()

    @property
    def silent(self) -> bool:
        return self.dry_run or self.link is None

    def boot_ms(self) -> int:
        return int((self._now_s() - self._start_s) * 1000.0) & UINT32_MASK

    def _send(self, encode: Callable[[Any], Any]) -> bool:
        if self.silent:
            return False
        assert self.link is not None
        try:
            self.link.send(encode(self.link.mav))
        except Exception as err:  # a value pymavlink cannot pack, a closed socket: never fatal
            self.send_errors += 1
            kind = type(err).__name__
            if kind not in self._logged:
                self._logged.add(kind)
                log.warning("outbox.send_failed", extra={"error": f"{kind}: {err}"})
            return False
        return True

    def counts(self) -> dict[str, int]:
        return {
            "setpoints_sent": self.setpoints_sent,
            "statustexts_sent": self.statustexts_sent,
            "clamped_values": self.clamped_values,
            "unsendable": self.unsendable,
            "send_errors": self.send_errors,
        }

    def command_long(self, command: int, *params: float) -> None:
        p = [*params, *([0.0] * (7 - len(params)))]
        if not float32_ok(p):
            self.unsendable += 1
            return
        self._send(lambda mav: mav.command_long_encode(*self.target, command, 0, *p))

    def ack(self, command: int, result: int, target_system: int, target_component: int) -> None:
        self._send(lambda mav: mav.command_ack_encode(command, result, 0, 0, target_system, target_component))

    def setpoint(self, sp: Setpoint) -> bool:
        """Send ``sp``; False when it could not be sent (unsendable, a send error, or silent)."""
        if not float32_ok((*sp.pos_ned_m, *sp.vel_ned_m_s)):
            self.unsendable += 1
            return False
        sent = self._send(
            lambda mav: encode_setpoint(
                mav, sp, time_boot_ms=self.boot_ms(), target_system=self.target[0], target_component=self.target[1]
            )
        )
        self.setpoints_sent += int(sent)
        if sent:
            self.last_setpoint = sp
        return sent

    def heartbeat(self, system_status: int) -> None:
        self._send(
            lambda mav: mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink.MAV_AUTOPILOT_INVALID,
                0,
                0,
                system_status,
            )  # mavlink_version: the encoder's default (3)
        )

    def statustext(self, severity: int, text: str) -> None:
        payload = text.encode("ascii", "replace")[:STATUSTEXT_BYTES]
        sent = self._send(lambda mav: mav.statustext_encode(severity, payload))
        self.statustexts_sent += int(sent)

    def named_value_float(self, name: str, value: float) -> None:
        t = self.boot_ms()
        v = clamp_float32(float(value))
        self.clamped_values += int(v != value)
        self._send(lambda mav: mav.named_value_float_encode(t, name.encode(), v))

    def named_value_int(self, name: str, value: int) -> None:
        """NAMED_VALUE_INT (int32 on the wire: saturated)."""
        t = self.boot_ms()
        v = max(-(2**31), min(2**31 - 1, int(value)))
        self.clamped_values += int(v != value)
        self._send(lambda mav: mav.named_value_int_encode(t, name.encode(), v))

    def set_mode(self, profile: Autopilot) -> None:
        """DO_SET_MODE for GUIDED (ArduCopter) / OFFBOARD (PX4)."""
        flag = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
        if profile is Autopilot.ARDUPILOT:
            self.command_long(mavlink.MAV_CMD_DO_SET_MODE, flag, float(CopterMode.GUIDED))
        else:
            self.command_long(mavlink.MAV_CMD_DO_SET_MODE, flag, float(PX4_OFFBOARD.main), float(PX4_OFFBOARD.sub))

    def arm(self) -> None:
        self.command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)

    def takeoff(self, param7_m: float) -> None:
        self.command_long(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, param7_m)

    def request_streams(self, telemetry_rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL for the pose streams, and GLOBAL_POSITION_INT at 5 Hz."""
        interval_us = 1e6 / telemetry_rate_hz
        for msg_id in STREAM_INTERVALS:
            self.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)
        self.command_long(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            float(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT),
            GLOBAL_POSITION_INTERVAL_US,
        )
