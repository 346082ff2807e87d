"""Everything the service sends to the autopilot, encoded with pymavlink's dialect constants.

Silent (nothing on the wire) in a dry run or without a link. ``time_boot_ms`` of outgoing messages counts from the
outbox's creation on the service clock.

Never raises on a value (docs/hardening.md, "never crash on data"): a float field that float32 cannot represent
(|v| > 3.4e38, which pymavlink's ``struct.pack`` refuses) is clamped in a report (NAMED_VALUE_FLOAT, counted in
``clamped_values``) and makes a setpoint or command unsendable (skipped, counted in ``unsendable``); any packing
or sending error is counted in ``send_errors`` and logged once per kind.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.adopt import SentSetpoints
from apf_companion.autopilot import PX4_OFFBOARD, Autopilot, CopterMode
from apf_companion.links import MavlinkLink
from apf_companion.setpoint import Setpoint, encode_setpoint

__all__ = ["FLOAT32_MAX", "Outbox", "float32_ok", "statustext_chunks"]

log = logging.getLogger(__name__)

FLOAT32_MAX = 3.4028234663852886e38  # MAVLink float fields are IEEE float32

STATUSTEXT_BYTES = 50  # one STATUSTEXT's text field
STATUSTEXT_MAX_CHUNKS = 4  # a longer text is cut at 199 bytes: a report, not a log (no flood on the link)
UINT32_MASK = 0xFFFFFFFF


def float32_ok(values: Iterable[float]) -> bool:
    """Every value fits a MAVLink float field (finite or NaN, |v| <= float32 max; inf is left to the caller)."""
    return all(not (abs(v) > FLOAT32_MAX and math.isfinite(v)) for v in values)


def clamp_float32(value: float) -> float:
    """``value`` clamped into float32's finite range (NaN stays NaN)."""
    return value if math.isnan(value) else max(-FLOAT32_MAX, min(FLOAT32_MAX, value))


def _encode_statustext(severity: int, text: bytes, chunk_id: int, chunk_seq: int, mav: Any) -> Any:
    return mav.statustext_encode(severity, text, chunk_id, chunk_seq)


def statustext_chunks(text: str, last_id: int) -> list[tuple[int, int, bytes]]:
    """(id, chunk_seq, text bytes) of each STATUSTEXT carrying ``text``.

    common.xml STATUSTEXT: ``id`` 0 marks a text that fits one message; a longer one shares a non-zero ``id``
    over chunks numbered from 0 by ``chunk_seq``, and a NUL in a chunk's text ends it. A text filling its last
    chunk exactly is followed by an empty chunk, so the receiver need not wait for a timeout. Cut at
    ``STATUSTEXT_MAX_CHUNKS`` chunks, the last of them one byte short so that it still ends the text (the NUL);
    non-ASCII characters become '?'.

    As ArduPilot's ``GCS::send_textv`` (libraries/GCS_MAVLink/GCS_Common.cpp): a new non-zero id per long text
    (wrapping past 0), 50-byte chunks while the rest fills one, an empty chunk after a full last one, and at the
    queue's capacity the last chunk cut by one byte to be NUL-terminated. pymavlink / MAVProxy reassemble by id.
    """
    cap = STATUSTEXT_BYTES * STATUSTEXT_MAX_CHUNKS - 1  # the last chunk keeps room for its NUL
    data = text.encode("ascii", "replace")[:cap]
    if len(data) <= STATUSTEXT_BYTES:
        return [(0, 0, data)]
    chunk_id = last_id % 0xFFFF + 1  # 1..65535, wrapping past 0
    parts = [data[i : i + STATUSTEXT_BYTES] for i in range(0, len(data), STATUSTEXT_BYTES)]
    if len(parts[-1]) == STATUSTEXT_BYTES:
        parts.append(b"")
    return [(chunk_id, seq, part) for seq, part in enumerate(parts)]


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
        self.sent = SentSetpoints()  # their positions: the autopilot's echoes of them are not new goals
        self.statustexts_sent = 0
        self.obstacle_distances_sent = 0
        self._statustext_id = 0  # id of the last chunked STATUSTEXT (uint16, never 0: 0 means "one chunk")
        self.clamped_values = 0  # report values clamped into float32's range
        self.unsendable = 0  # setpoints / commands with a value float32 cannot carry: not sent
        self.send_errors = 0  # packing or sending raised: counted, logged once per kind
        self.stream_requests = 0  # SET_MESSAGE_INTERVAL commands sent
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
            "obstacle_distances_sent": self.obstacle_distances_sent,
            "clamped_values": self.clamped_values,
            "unsendable": self.unsendable,
            "send_errors": self.send_errors,
            "stream_requests": self.stream_requests,
        }

    def command_long(self, command: int, *params: float) -> None:
        p = [*params, *([0.0] * (7 - len(params)))]
        if not float32_ok(p):
            self.unsendable += 1
            return
        self._send(lambda mav: mav.command_long_encode(*self.target, command, 0, *p))

    def ack(self, command: int, result: int, target_system: int, target_component: int) -> None:
        self._send(lambda mav: mav.command_ack_encode(command, result, 0, 0, target_system, target_component))

    def mission_request(self, mission_type: int, seq: int | None) -> None:
        """MISSION_REQUEST_LIST (``seq`` None) or MISSION_REQUEST_INT of item ``seq``, of ``mission_type``."""
        if seq is None:
            self._send(lambda mav: mav.mission_request_list_encode(*self.target, mission_type=mission_type))
        else:
            self._send(lambda mav: mav.mission_request_int_encode(*self.target, seq, mission_type=mission_type))

    def param_request_read(self, name: str) -> None:
        """PARAM_REQUEST_READ of the autopilot's parameter ``name`` (by name: param_index -1)."""
        self._send(lambda mav: mav.param_request_read_encode(*self.target, name.encode("ascii"), -1))

    def mission_ack(self, result: int, mission_type: int) -> None:
        """MISSION_ACK: the end of a download (MAV_MISSION_ACCEPTED) of ``mission_type``."""
        self._send(lambda mav: mav.mission_ack_encode(*self.target, result, mission_type=mission_type))

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
            self.sent.add(self._now_s(), sp.pos_ned_m)
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
        """STATUSTEXT; a text longer than one message goes in chunks (MAVLink 2 ``id`` / ``chunk_seq``)."""
        for chunk_id, seq, payload in statustext_chunks(text, self._statustext_id):
            self._statustext_id = chunk_id or self._statustext_id
            sent = self._send(functools.partial(_encode_statustext, severity, payload, chunk_id, seq))
            self.statustexts_sent += int(sent)

    def param_value(self, name: str, value: float, mav_type: int, count: int, index: int) -> None:
        """PARAM_VALUE (apf_companion.params): ``index`` -1 answers a PARAM_SET (uint16 on the wire: 65535, as
        ArduPilot's -1 arrives)."""
        v = clamp_float32(float(value))
        i = index & 0xFFFF
        self._send(lambda mav: mav.param_value_encode(name.encode("ascii"), v, mav_type, count, i))

    def obstacle_distance(self, time_usec: int, distances_cm: tuple[int, ...], min_cm: int, max_cm: int) -> bool:
        """OBSTACLE_DISTANCE in body FRD: element j at j * 5 deg clockwise from the nose (AP_Proximity_MAV.cpp
        reads ``j * increment + angle_offset`` in the body frame); True when it went out."""
        increment_deg = 360 // len(distances_cm)
        sent = self._send(
            lambda mav: mav.obstacle_distance_encode(
                time_usec & 0xFFFFFFFFFFFFFFFF,
                mavlink.MAV_DISTANCE_SENSOR_UNKNOWN,  # a fused view of every sensor, not one device
                list(distances_cm),
                increment_deg,
                min_cm,
                max_cm,
                increment_f=float(increment_deg),
                angle_offset=0.0,
                frame=mavlink.MAV_FRAME_BODY_FRD,
            )
        )
        self.obstacle_distances_sent += int(sent)
        return sent

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

    def request_streams(self, rates_hz: Mapping[int, float]) -> None:
        """SET_MESSAGE_INTERVAL for each message id at its rate [Hz] (apf_companion.streams says which)."""
        for msg_id, rate_hz in rates_hz.items():
            self.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), 1e6 / rate_hz)
            self.stream_requests += 1
