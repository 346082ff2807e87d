"""The telemetry streams asked of the autopilot (``StreamKeeper``, apf_companion/streams.py): each record from the
autopilot counts for its stream, a HEARTBEAT sends the requests that are due, and streams that came too slowly are
counted (``slow_streams``) and said (``streams.slow``, rate-limited) with the likely cause."""

from __future__ import annotations

import logging

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.handling.params import HandlerParams
from apf_companion.links.messages import (
    Attitude,
    EkfStatusReport,
    GlobalPositionInt,
    LocalPositionNed,
    Record,
    SysStatus,
)
from apf_companion.outbox import Outbox
from apf_companion.perception.ratelog import RateLimitedLog
from apf_companion.reporter import ServiceCounters
from apf_companion.streams import StreamKeeper, wanted_streams

__all__ = ["SLOW_STREAMS_LOG_INTERVAL_S", "StreamRequests"]

log = logging.getLogger("apf_companion.handlers")  # the logger its lines had before the handlers' split
SLOW_STREAMS_LOG_INTERVAL_S = 60.0  # ``streams.slow``: the first at once, then at most one line a minute
_STREAM_OF = {
    LocalPositionNed: mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    Attitude: mavlink.MAVLINK_MSG_ID_ATTITUDE,
    GlobalPositionInt: mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    EkfStatusReport: mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
    SysStatus: mavlink.MAVLINK_MSG_ID_SYS_STATUS,
}


class StreamRequests:
    """Owns the ``StreamKeeper`` (``keeper``) and the ``streams.slow`` log; sends through the outbox."""

    def __init__(self, params: HandlerParams, *, outbox: Outbox, counters: ServiceCounters) -> None:
        self.keeper = StreamKeeper(
            wanted_streams(params.profile, params.telemetry_rate_hz, targets=params.adopt.enabled)
        )
        self._outbox = outbox
        self._counters = counters
        self._slow_log = RateLimitedLog(log, "streams.slow", SLOW_STREAMS_LOG_INTERVAL_S)

    def heard(self, rec: Record, now_s: float) -> None:
        """A record from the autopilot at ``now_s``: it counts for its stream (if it is one we ask for)."""
        stream = _STREAM_OF.get(type(rec))
        if stream is not None:
            self.keeper.heard(stream, now_s)

    def restart(self) -> None:
        """The autopilot (re)booted or came back: it has forgotten our requests."""
        self.keeper.restart()

    def send_due(self, now_s: float) -> None:
        """At a HEARTBEAT: ask for the streams that are due (again)."""
        rates = self.keeper.due(now_s)
        if rates:
            self._outbox.request_streams(rates)
            if self.keeper.last_slow:
                self._slow(now_s)

    def _slow(self, now_s: float) -> None:
        """Asked again for streams that arrived too slowly: counted, and said (rate-limited) with the likely cause."""
        self._counters.slow_streams += 1
        slow = {
            _message_name(i): f"{hz:.1f} of {self.keeper.rates_hz[i]:g} Hz" for i, hz in self.keeper.last_slow.items()
        }
        self._slow_log.note(
            now_s,
            streams=slow,
            hint="something on this link lowered the rates, e.g. a ground station's REQUEST_DATA_STREAM through the "
            "same router; asked again. ArduPilot: SERIALn_OPTIONS bit 12 makes the port ignore such requests",
        )


def _message_name(msg_id: int) -> str:
    """A message's name from pymavlink's dialect (its id where the dialect has none)."""
    entry = mavlink.mavlink_map.get(msg_id)
    return str(entry.msgname) if entry is not None else str(msg_id)
