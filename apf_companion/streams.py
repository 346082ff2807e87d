"""The telemetry the service needs, asked for and kept coming: an autopilot sends little unasked.

A fresh ArduCopter sends only HEARTBEAT until a ground station or companion requests streams (its SRn_* / MAVn_*
stream rates default to 0; SITL, issue 8), and it forgets every request when it reboots. ``StreamKeeper`` asks
(SET_MESSAGE_INTERVAL, one per message) when the autopilot is first heard, again when it reboots or the link
comes back, and again while a requested message stays missing (``STREAM_STALE_S``), at most every
``STREAM_RETRY_S``. LOCAL_POSITION_NED is missing until the EKF has an origin (ArduCopter: no position relative to
an origin yet, ``GCS_Common.cpp`` send_local_position), so the request is repeated then too: harmless, one
COMMAND_LONG per message every few seconds.

Pure: the caller passes the time (service seconds) and sends what ``due`` returns.
"""

from __future__ import annotations

from collections.abc import Mapping

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot

__all__ = ["STREAM_RETRY_S", "STREAM_STALE_S", "StreamKeeper", "wanted_streams"]

STREAM_STALE_S = 3.0  # a requested message not heard for this long is asked for again
STREAM_RETRY_S = 5.0  # at most this often
GLOBAL_POSITION_HZ = 5.0  # only the takeoff (PX4: AMSL) and DO_REPOSITION use it
EKF_STATUS_HZ = 2.0  # readiness before taking over (ArduPilot)
SYS_STATUS_HZ = 1.0  # whether ArduPilot's fence is switched on (its GEOFENCE bit; apf_companion.fencelimits)


def wanted_streams(profile: Autopilot, telemetry_rate_hz: float, *, targets: bool = False) -> dict[int, float]:
    """The messages the service consumes from the autopilot, with their rates [Hz]: the pose at the telemetry
    rate, the global reference for goals and the PX4 takeoff, (ArduPilot) the EKF status and SYS_STATUS (is the
    fence switched on), and with ``targets``
    (goal adoption, apf_companion.adopt) the autopilot's POSITION_TARGET_* reports (ArduPilot sends them in its
    EXTENDED_STATUS stream, which a companion port may not have)."""
    out = {
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: telemetry_rate_hz,
        mavlink.MAVLINK_MSG_ID_ATTITUDE: telemetry_rate_hz,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: GLOBAL_POSITION_HZ,
    }
    if profile is Autopilot.ARDUPILOT:
        out[mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT] = EKF_STATUS_HZ
        out[mavlink.MAVLINK_MSG_ID_SYS_STATUS] = SYS_STATUS_HZ
    if targets:
        out[mavlink.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT] = GLOBAL_POSITION_HZ
        out[mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED] = GLOBAL_POSITION_HZ
    return out


class StreamKeeper:
    """When to (re-)request the streams in ``rates_hz`` (message id -> Hz)."""

    def __init__(self, rates_hz: Mapping[int, float]) -> None:
        self.rates_hz = dict(rates_hz)
        self.last_heard_s: dict[int, float] = {}
        self.requested_s: float | None = None
        self.requests = 0  # times the set was (re-)requested

    def heard(self, msg_id: int, now_s: float) -> None:
        if msg_id in self.rates_hz:
            self.last_heard_s[msg_id] = now_s

    def restart(self) -> None:
        """The autopilot rebooted or the link came back: it may have forgotten every request."""
        self.requested_s = None
        self.last_heard_s.clear()

    def missing(self, now_s: float) -> list[int]:
        """Requested messages not heard within ``STREAM_STALE_S`` (of the request, or of the last one heard)."""
        since = self.requested_s if self.requested_s is not None else now_s
        return [
            msg_id
            for msg_id in self.rates_hz
            if now_s - max(self.last_heard_s.get(msg_id, since), since) > STREAM_STALE_S
        ]

    def due(self, now_s: float) -> dict[int, float]:
        """The streams to request now (all of them: first time, after ``restart``, or when one is missing and
        the last request is ``STREAM_RETRY_S`` old); empty otherwise."""
        if self.requested_s is not None and (now_s - self.requested_s < STREAM_RETRY_S or not self.missing(now_s)):
            return {}
        self.requested_s = now_s
        self.requests += 1
        return dict(self.rates_hz)
