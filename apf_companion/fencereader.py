"""Reads the autopilot's fence once, for bapf-nav's flying area (``apf_companion.fence`` has the protocol's state
and the geometry; this drives it with what the other parts know).

The download starts when the autopilot has been heard and the global reference (GLOBAL_POSITION_INT beside a
local pose) can place latitude/longitude in local NED. The autopilot's answers (MISSION_COUNT, MISSION_ITEM_INT,
MISSION_ACK) count only when addressed to us and of mission type FENCE: a ground station downloading its own
fence on the same link does not feed ours. When the download ends, ``on_area`` gets the result once: the area,
or None and why. ``due`` is stepped by the service's ``apf.fence`` task on the service clock.
"""

from __future__ import annotations

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
#: The step after the reader has finished [s]: it has nothing more to do.
IDLE_S = 3600.0


@dataclass(frozen=True, slots=True, kw_only=True)
class FenceReaderParams:
    """Our ids (the answers' target), the autopilot's, and the download's patience: ``timeout_s`` [s] between
    repeats of a request, ``retries`` repeats."""

    our_system: int
    our_component: int
    autopilot: Source
    timeout_s: float = 1.0
    retries: int = 5


class FenceReader:
    """The fence download of one service run (module docstring)."""

    def __init__(
        self,
        params: FenceReaderParams,
        *,
        outbox: Outbox,
        reference: Callable[[], tuple[GlobalReference, tuple[float, float]] | None],
        on_area: Callable[[FenceArea], None],
    ) -> None:
        """``reference()``: the global reference and the vehicle's (north, east) [m] now, or None if not known."""
        self.params = params
        self.download = FenceDownload(params.timeout_s, params.retries)
        self.result: FenceArea | None = None
        #: Mission answers that were not for us or not about the fence: dropped.
        self.ignored = 0
        self._outbox = outbox
        self._reference = reference
        self._on_area = on_area

    def on_record(self, rec: MissionRecord) -> None:
        """An answer from the autopilot: to the download when addressed to us and about the fence."""
        p = self.params
        ours = rec.target_system == p.our_system and rec.target_component == p.our_component
        if not ours or rec.mission_type != _FENCE or self.result is not None:
            self.ignored += 1
        elif isinstance(rec, MissionCount):
            self.download.on_count(rec.count)
        elif isinstance(rec, MissionItemInt):
            self.download.on_item(FenceItem(seq=rec.seq, command=rec.command, param1=rec.param1, x=rec.x, y=rec.y))
        else:
            self.download.on_ack(rec.type)

    def due(self, now_s: float) -> float:
        """Start, send what is due, finish; the time of the next step."""
        if self.result is not None:
            return now_s + IDLE_S
        d = self.download
        if d.stage is FenceStage.IDLE and self._reference() is not None:
            d.start()
        send = d.due(now_s)
        if send is not None and send.ack:
            self._outbox.mission_ack(mavlink.MAV_MISSION_ACCEPTED, _FENCE)
        elif send is not None:
            self._outbox.mission_request(_FENCE, send.seq)
        if d.stage is FenceStage.DONE and send is None:  # after the closing ack went out
            self._finish()
        elif d.stage is FenceStage.FAILED:
            self._finish_with(FenceArea(FenceOutcome.FAILED, f"download failed: {d.reason}"))
        return now_s + STEP_S

    def _finish(self) -> None:
        where = self._reference()
        if where is None:  # the reference went away (a reboot) between start and end: not placed
            self._finish_with(FenceArea(FenceOutcome.NOT_USED, "no global reference to place the fence"))
        else:
            self._finish_with(fence_area(self.download.items, *where))

    def _finish_with(self, result: FenceArea) -> None:
        self.result = result
        self._on_area(result)
