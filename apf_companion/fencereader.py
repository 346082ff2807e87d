"""Reads the autopilot's fence for bapf-nav's flying area, at start and again every ``poll_s`` in flight
(``apf_companion.fence`` has the protocol's state and the geometry; this drives it with what the other parts know).

The first download starts when the autopilot has been heard and the global reference (GLOBAL_POSITION_INT beside
a local pose) can place latitude/longitude in local NED. The autopilot's answers (MISSION_COUNT, MISSION_ITEM_INT,
MISSION_ACK) count only when addressed to us and of mission type FENCE: a ground station downloading its own
fence on the same link does not feed ours.

Why poll: a ground station that uploads a new fence tells only itself (the closing MISSION_ACK goes to the
uploader), and the plan-change ids of MAVLink's MISSION_CURRENT (``fence_id``) are not in pymavlink's dialect
(2.4.50) nor sent by every autopilot. So the fence is read again every ``poll_s``; a fence of 10 vertices costs
23 small messages, 718 bytes. ``on_area`` gets a result when it differs from the last one: the first read
(whatever it gave), then a fence whose items changed (compared item by item, in 1e-7 degrees, so the global
reference's centimetre jitter moves nothing), or the same fence when it was not used and now is (the vehicle, outside
it at the last read, has flown in). A later read that fails (a ground station uploading answers DENIED)
keeps what is in service and is counted; the next read comes ``poll_s`` later. ``due`` is stepped by the service's
``apf.fence`` task on the service clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.fence import FenceArea, FenceDownload, FenceItem, FenceOutcome, FenceStage, fence_area
from apf_companion.goal import GlobalReference
from apf_companion.links.messages import MissionCount, MissionItemInt, MissionRecord, Source
from apf_companion.outbox import Outbox

__all__ = ["FenceReader", "FenceReaderParams"]

_FENCE = mavlink.MAV_MISSION_TYPE_FENCE
#: How often the reader is stepped while it downloads [s] (a request's repeat comes after ``timeout_s``).
STEP_S = 0.1
#: The longest step between reads [s]: a PARAM_SET may change ``poll_s`` (0 = read once) at any time.
IDLE_S = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class FenceReaderParams:
    """Our ids (the answers' target), the autopilot's, the download's patience (``timeout_s`` [s] between repeats
    of a request, ``retries`` repeats) and ``poll_s`` [s] from the end of one read to the start of the next
    (0: read once)."""

    our_system: int
    our_component: int
    autopilot: Source
    timeout_s: float = 1.0
    retries: int = 5
    poll_s: float = 5.0


class FenceReader:
    """The fence downloads of one service run (module docstring)."""

    def __init__(
        self,
        params: FenceReaderParams,
        *,
        outbox: Outbox,
        reference: Callable[[], tuple[GlobalReference, tuple[float, float]] | None],
        on_area: Callable[[FenceArea], None],
    ) -> None:
        """``reference()``: the global reference and the vehicle's (north, east) [m] now, or None if not known."""
        #: Replaced when a PARAM_SET changes ``planner.fence_poll_s`` (APF_FENCE_POLL); ``due`` follows it at once.
        self.params = params
        self.download = FenceDownload(params.timeout_s, params.retries)
        #: The last result given to ``on_area`` (None before the first read has ended).
        self.result: FenceArea | None = None
        #: Downloads that ended: read whole, and failed.
        self.reads = 0
        self.failures = 0
        #: Reads whose fence differed from the one before (the first read not counted).
        self.changes = 0
        #: Mission answers that were not for us, not about the fence, or came with no download running: dropped.
        self.ignored = 0
        self._outbox = outbox
        self._reference = reference
        self._on_area = on_area
        self._items: tuple[FenceItem, ...] | None = None  # of the last read that ended whole
        self._ended_s = -math.inf  # when the last download ended

    def summary(self) -> dict[str, object]:
        """The status record's ``fence``: the last result (None before the first read ended) and the counters."""
        r = self.result
        return {
            "outcome": None if r is None else r.outcome.value,
            "note": None if r is None else r.note,
            "reads": self.reads,
            "failures": self.failures,
            "changes": self.changes,
            "ignored": self.ignored,
            "unexpected": self.download.unexpected,
        }

    def on_record(self, rec: MissionRecord) -> None:
        """An answer from the autopilot: to the download when addressed to us, about the fence, and one runs."""
        p = self.params
        ours = rec.target_system == p.our_system and rec.target_component == p.our_component
        if not ours or rec.mission_type != _FENCE or self.download.stage not in _RUNNING:
            self.ignored += 1
        elif isinstance(rec, MissionCount):
            self.download.on_count(rec.count)
        elif isinstance(rec, MissionItemInt):
            self.download.on_item(FenceItem(seq=rec.seq, command=rec.command, param1=rec.param1, x=rec.x, y=rec.y))
        else:
            self.download.on_ack(rec.type)

    def due(self, now_s: float) -> float:
        """Start a read when one is due, send what is due, finish; the time of the next step."""
        d = self.download
        if d.stage is FenceStage.IDLE:
            if self.result is not None and self.params.poll_s <= 0.0:
                return now_s + IDLE_S
            next_read_s = self._ended_s + self.params.poll_s
            if now_s < next_read_s:
                return min(next_read_s, now_s + IDLE_S)
            if self._reference() is None:
                return now_s + STEP_S
            d.start()
        send = d.due(now_s)
        if send is not None and send.ack:
            self._outbox.mission_ack(mavlink.MAV_MISSION_ACCEPTED, _FENCE)
        elif send is not None:
            self._outbox.mission_request(_FENCE, send.seq)
        if d.stage is FenceStage.DONE and send is None:  # after the closing ack went out
            self._ended(now_s, whole=True)
        elif d.stage is FenceStage.FAILED:
            self._ended(now_s, whole=False)
        return now_s + STEP_S

    def _ended(self, now_s: float, *, whole: bool) -> None:
        """A download ended: the next is due ``poll_s`` later; its result goes out when it is news."""
        self._ended_s = now_s
        reason = self.download.reason
        self.download.rest()
        if not whole:
            self.failures += 1
            if self.result is None:  # the first read: say that there is no fence to plan over (yet)
                self._tell(FenceArea(FenceOutcome.FAILED, f"download failed: {reason}"))
            return
        self.reads += 1
        items = tuple(self.download.items)
        unused = self.result is not None and self.result.outcome is FenceOutcome.NOT_USED
        if items == self._items and not unused:
            return
        where = self._reference()
        if where is None:  # the reference went away (a reboot) between start and end: placed at the next read
            if self.result is None:
                self._tell(FenceArea(FenceOutcome.NOT_USED, "no global reference to place the fence"))
            return
        result = fence_area(items, *where)
        if items == self._items and result == self.result:  # still not used, for the same reason
            return
        self.changes += self._items is not None
        self._items = items
        self._tell(result)

    def _tell(self, result: FenceArea) -> None:
        self.result = result
        self._on_area(result)


_RUNNING = (FenceStage.COUNT, FenceStage.ITEMS)
