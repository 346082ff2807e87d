"""The telemetry the service needs, asked for and kept coming: an autopilot sends little unasked.

A fresh ArduCopter sends only HEARTBEAT until a ground station or companion requests streams (its SRn_* / MAVn_*
stream rates default to 0; SITL, issue 8), and it forgets every request when it reboots. ``StreamKeeper`` asks
(SET_MESSAGE_INTERVAL, one per message) when the autopilot is first heard, again when it reboots or the link
comes back, and again while a requested message stays missing (``STREAM_STALE_S``), at most every
``STREAM_RETRY_S``. LOCAL_POSITION_NED is missing until the EKF has an origin (ArduCopter: no position relative to
an origin yet, ``GCS_Common.cpp`` send_local_position), so the request is repeated then too: harmless, one
COMMAND_LONG per message every few seconds.

A stream can also slow down: a ground station that shares the companion's link (through mavlink-router, MAVProxy)
sends REQUEST_DATA_STREAM, and ArduPilot applies its rate to every message of that stream on the link
(``GCS_Param.cpp`` handle_request_data_stream; MAVProxy asks for 4 Hz at start and every 15 s), so a 20 Hz pose
becomes 4 Hz and the planner cycles at 4 Hz. Each message's rate is measured over ``STREAM_RATE_WINDOW_S``; one
that arrives at less than ``STREAM_SLOW_FRACTION`` of its rate is asked for again too (``slow``: the caller says
so; ArduPilot's ``SERIALn_OPTIONS`` bit 12 makes the port ignore other stream requests).

Pure: the caller passes the time (service seconds) and sends what ``due`` returns.
"""

from __future__ import annotations

from collections.abc import Mapping

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot

__all__ = [
    "STREAM_RATE_WINDOW_S",
    "STREAM_RETRY_S",
    "STREAM_SLOW_FRACTION",
    "STREAM_STALE_S",
    "StreamKeeper",
    "wanted_streams",
]

STREAM_STALE_S = 3.0  # a requested message not heard for this long is asked for again
STREAM_RETRY_S = 5.0  # at most this often
STREAM_RATE_WINDOW_S = 5.0  # each message's rate is measured over this long
STREAM_SLOW_FRACTION = 0.5  # a message arriving at less than this share of its rate is asked for again
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
        self.slow_requests = 0  # of those, because a message arrived too slowly (``slow``)
        self.last_slow: dict[int, float] = {}  # the slow messages behind the last request (id -> measured Hz)
        self.measured_hz: dict[int, float] = {}  # each message's rate over the last full window
        self._counts: dict[int, int] = {}
        self._window_s: float | None = None  # start of the window being counted (None: not counting)

    def heard(self, msg_id: int, now_s: float) -> None:
        if msg_id in self.rates_hz:
            self.last_heard_s[msg_id] = now_s
            self._counts[msg_id] = self._counts.get(msg_id, 0) + 1

    def restart(self) -> None:
        """The autopilot rebooted or the link came back: it may have forgotten every request."""
        self.requested_s = None
        self.last_heard_s.clear()
        self._forget_rates()

    def missing(self, now_s: float) -> list[int]:
        """Requested messages not heard within ``STREAM_STALE_S`` (of the request, or of the last one heard)."""
        since = self.requested_s if self.requested_s is not None else now_s
        return [
            msg_id
            for msg_id in self.rates_hz
            if now_s - max(self.last_heard_s.get(msg_id, since), since) > STREAM_STALE_S
        ]

    def slow(self) -> dict[int, float]:
        """Messages that arrive, but at less than ``STREAM_SLOW_FRACTION`` of their rate over the last full window
        since the last request: message id -> measured Hz."""
        return {
            msg_id: hz
            for msg_id, hz in self.measured_hz.items()
            if 0.0 < hz < STREAM_SLOW_FRACTION * self.rates_hz[msg_id]
        }

    def due(self, now_s: float) -> dict[int, float]:
        """The streams to request now (all of them: first time, after ``restart``, or when one is missing or slow
        and the last request is ``STREAM_RETRY_S`` old); empty otherwise."""
        self._measure(now_s)
        if self.requested_s is not None and now_s - self.requested_s < STREAM_RETRY_S:
            return {}
        slow = self.slow()
        if self.requested_s is not None and not slow and not self.missing(now_s):
            return {}
        self.requested_s = now_s
        self.requests += 1
        self.slow_requests += int(bool(slow))
        self.last_slow = slow
        self._forget_rates()
        self._window_s = now_s  # the rates count from this request
        return dict(self.rates_hz)

    def _measure(self, now_s: float) -> None:
        """Close the window once it is ``STREAM_RATE_WINDOW_S`` long: each message's rate over it."""
        start = self._window_s
        if start is None or now_s - start < STREAM_RATE_WINDOW_S:
            return
        span = now_s - start
        self.measured_hz = {msg_id: self._counts.get(msg_id, 0) / span for msg_id in self.rates_hz}
        self._counts.clear()
        self._window_s = now_s

    def _forget_rates(self) -> None:
        self.measured_hz = {}
        self._counts.clear()
        self._window_s = None
