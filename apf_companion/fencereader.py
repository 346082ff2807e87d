"""Reads the autopilot's fence for bapf-nav's flying area, at start and again every ``poll_s`` in flight
(``apf_companion.fence`` has the protocol's state and the geometry, ``apf_companion.fencelimits`` the fence
parameters; this drives them with what the other parts know).

A read asks for the fence parameters first (PARAM_REQUEST_READ of ``FENCE_PARAMS[profile]``: which fences are
configured and on, the margin, the circle round home and the ceiling) and for HOME_POSITION
(MAV_CMD_REQUEST_MESSAGE: the circle's centre), then downloads the items. Parameters that cannot be read (an
autopilot without them stays silent) leave every uploaded zone in use, as before the parameters were read, and
the note says so.

The first download starts when the autopilot has been heard and the global reference (GLOBAL_POSITION_INT beside
a local pose) can place latitude/longitude in local NED. The autopilot's answers (MISSION_COUNT, MISSION_ITEM_INT,
MISSION_ACK) count only when addressed to us and of mission type FENCE: a ground station downloading its own
fence on the same link does not feed ours.

Why poll: a ground station that uploads a new fence tells only itself (the closing MISSION_ACK goes to the
uploader). So the fence is read again every ``poll_s``; a fence of 10 vertices costs 23 small messages, 718 bytes.
An autopilot that gives its fence plan an id (PX4: MISSION_CURRENT ``fence_id`` at 1 Hz and MISSION_COUNT
``opaque_id``, the CRC32 of its items; ArduPilot 4.6 sends none) is spared the items' download: when a
MISSION_CURRENT heard since the last read ended gives the id of the items in service, the read takes the
parameters only (``skipped``). That matters on PX4, whose one transfer state refuses a ground station's upload
while we download. An id of 0 (no fence, or no ids) always downloads. A MISSION_CURRENT whose id differs from the
one in service starts a read at once (``early``): a fence changed on PX4 is in service a second or two later.

``on_area`` gets a result when it differs from the last one: the first read (whatever it gave), then a fence whose
items or parameters changed (compared as sent, items in 1e-7 degrees, so the global reference's centimetre jitter
moves nothing), or the same fence when it was not used and now is (the vehicle, outside it at the last read, has
flown in) or was used provisionally and now is whole (home heard, the vehicle out of the margin). A later read that
fails (a ground station uploading answers DENIED) keeps what is in service and is counted; the next read comes
``poll_s`` later. ``due`` is stepped by the service's ``apf.fence`` task on the service clock.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from apf_companion.fence import FenceArea, FenceDownload, FenceItem, FenceOutcome, FenceStage, fence_area
from apf_companion.fencelimits import (
    FENCE_PARAMS,
    OPTIONAL_PARAMS,
    FenceLimits,
    ParamRead,
    ReadStage,
    fence_limits,
    param_float,
)
from apf_companion.goal import FenceBounds, GlobalReference
from apf_companion.links.messages import (
    FenceRecord,
    HomePosition,
    MissionAck,
    MissionCount,
    MissionCurrent,
    MissionItemInt,
    ParamValue,
    Source,
    SysStatus,
)
from apf_companion.outbox import Outbox

__all__ = ["FenceReader", "FenceReaderParams"]

log = logging.getLogger(__name__)

_FENCE = mavlink.MAV_MISSION_TYPE_FENCE
#: How often the reader is stepped while it downloads [s] (a request's repeat comes after ``timeout_s``).
STEP_S = 0.1
#: The longest step between reads [s]: a PARAM_SET may change ``poll_s`` (0 = read once) at any time.
IDLE_S = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class FenceReaderParams:
    """Our ids (the answers' target), the autopilot's and its kind (which fence parameters), the read's patience
    (``timeout_s`` [s] between repeats of a request, ``retries`` repeats) and ``poll_s`` [s] from the end of one
    read to the start of the next (0: read once)."""

    our_system: int
    our_component: int
    autopilot: Source
    profile: Autopilot = Autopilot.ARDUPILOT
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
        clearance_m: Callable[[], float] = lambda: 0.0,
    ) -> None:
        """``reference()``: the global reference and the vehicle's (north, east) [m] now, or None if not known;
        ``clearance_m()``: the planner's clearance C [m], which keeps that much of the fence's margin."""
        #: Replaced when a PARAM_SET changes ``planner.fence_poll_s`` (APF_FENCE_POLL); ``due`` follows it at once.
        self.params = params
        self.download = FenceDownload(params.timeout_s, params.retries)
        self.param_read = ParamRead(
            FENCE_PARAMS[params.profile], params.timeout_s, params.retries, optional=OPTIONAL_PARAMS[params.profile]
        )
        #: The last parameters read as limits, or why they could not be (None before the first read ended).
        self.limits: FenceLimits | str | None = None
        #: HOME_POSITION's latitude, longitude [1e-7 deg] (None until heard).
        self.home: tuple[int, int] | None = None
        #: ArduPilot's SYS_STATUS says its fence is switched on (GEOFENCE enabled); False until heard.
        self.switched_on = False
        #: ... and breached now (GEOFENCE present, not healthy: ``GCS.cpp``, ``!fence->sys_status_failed()``), and
        #: how often it was newly breached.
        self.breached = False
        self.breaches = 0
        #: The last result given to ``on_area`` (None before the first read has ended).
        self.result: FenceArea | None = None
        #: Reads that ended: whole (downloaded, or vouched for by the fence id: ``skipped``), and failed downloads.
        self.reads = 0
        self.failures = 0
        #: Reads whose fence differed from the one before (the first read not counted).
        self.changes = 0
        #: Reads without a download: the autopilot's fence id said the items in service are still its fence.
        self.skipped = 0
        #: Reads started before ``poll_s`` because the autopilot's fence id changed.
        self.early = 0
        #: Mission answers that were not for us, not about the fence, or came with no download running: dropped.
        self.ignored = 0
        self._outbox = outbox
        self._reference = reference
        self._on_area = on_area
        self._clearance_m = clearance_m
        self._inputs: tuple[object, ...] | None = None  # of the last read that ended whole: items, limits, home, C
        self._ended_s = -math.inf  # when the last download ended
        self._items: tuple[FenceItem, ...] = ()  # of the last download that ended whole
        self._items_id = 0  # their plan id (MISSION_COUNT opaque_id; 0: none given)
        self._id_heard: int | None = None  # MISSION_CURRENT fence_id, heard since the last read ended
        self._early_for: int | None = None  # the last id that started an early read

    def summary(self) -> dict[str, object]:
        """The status record's ``fence``: the last result (None before the first read ended) and the counters."""
        r = self.result
        return {
            "outcome": None if r is None else r.outcome.value,
            "note": None if r is None else r.note,
            "reads": self.reads,
            "failures": self.failures,
            "changes": self.changes,
            "skipped": self.skipped,
            "early": self.early,
            "breached": self.breached,
            "breaches": self.breaches,
            "ignored": self.ignored,
            "unexpected": self.download.unexpected,
            "limits": self.limits.note if isinstance(self.limits, FenceLimits) else self.limits,
            "ceiling_m": self.bounds.ceiling_m,
            "floor_m": self.bounds.floor_m,
            "home_circle_ne_m": self.bounds.home_circle,
        }

    @property
    def bounds(self) -> FenceBounds:
        """The fence's bounds for goals in service (its ceiling, its circle round home)."""
        r = self.result
        return FenceBounds() if r is None or r.outcome is not FenceOutcome.USED else r.bounds

    def on_param(self, rec: ParamValue) -> None:
        """A PARAM_VALUE from the autopilot: a fence parameter while they are read (anyone's answer will do)."""
        self.param_read.on_value(rec.param_id, param_float(rec.param_value, rec.param_type, self.params.profile))

    def on_home(self, rec: HomePosition) -> None:
        """HOME_POSITION from the autopilot: the centre of its circle round home."""
        self.home = (rec.latitude, rec.longitude)

    def on_mission_current(self, rec: MissionCurrent) -> None:
        """MISSION_CURRENT from the autopilot: the id of the fence it holds now (0: none, or no ids)."""
        self._id_heard = rec.fence_id

    def on_sys_status(self, rec: SysStatus) -> None:
        """SYS_STATUS from the autopilot: whether its fence is switched on now (read with the parameters), and
        breached (said in the status record; the autopilot's FENCE_ACTION acts on it, not the service)."""
        geofence = mavlink.MAV_SYS_STATUS_GEOFENCE
        self.switched_on = bool(rec.enabled & rec.present & geofence)
        breached = bool(rec.present & geofence) and not rec.health & geofence
        if breached and not self.breached:
            self.breaches += 1
            log.warning("fence.breached", extra={"breaches": self.breaches})
        self.breached = breached

    def on_record(self, rec: FenceRecord) -> None:
        """A record from the autopilot: a parameter, home, or an answer to the download when addressed to us,
        about the fence, and one runs."""
        if not isinstance(rec, MissionCount | MissionItemInt | MissionAck):
            _OTHER_RECORDS[type(rec)](self, rec)
            return
        p = self.params
        ours = rec.target_system == p.our_system and rec.target_component == p.our_component
        if not ours or rec.mission_type != _FENCE or self.download.stage not in _RUNNING:
            self.ignored += 1
        elif isinstance(rec, MissionCount):
            self.download.on_count(rec.count, rec.opaque_id)
        elif isinstance(rec, MissionItemInt):
            self.download.on_item(FenceItem(seq=rec.seq, command=rec.command, param1=rec.param1, x=rec.x, y=rec.y))
        else:
            self.download.on_ack(rec.type)

    def due(self, now_s: float) -> float:
        """Start a read when one is due, send what is due, finish; the time of the next step."""
        d = self.download
        if d.stage is FenceStage.IDLE:
            if self.param_read.stage is ReadStage.IDLE:
                wait_until_s = self._next_read_s(now_s)
                if wait_until_s is not None:
                    return wait_until_s
                self.param_read.start()
                self._outbox.command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, float(mavlink.MAVLINK_MSG_ID_HOME_POSITION))
            if not self._params_due(now_s):
                return now_s + STEP_S
            if self._items_id != 0 and self._id_heard == self._items_id:
                self.skipped += 1
                self._ended(now_s)
                return now_s + STEP_S
            d.start()
        send = d.due(now_s)
        if send is not None and send.ack:
            self._outbox.mission_ack(mavlink.MAV_MISSION_ACCEPTED, _FENCE)
        elif send is not None:
            self._outbox.mission_request(_FENCE, send.seq)
        if d.stage is FenceStage.DONE and send is None:  # after the closing ack went out
            self._items, self._items_id = tuple(d.items), d.plan_id
            d.rest()
            self._ended(now_s)
        elif d.stage is FenceStage.FAILED:
            reason = d.reason
            d.rest()
            self._ended(now_s, failed=reason)
        return now_s + STEP_S

    def _next_read_s(self, now_s: float) -> float | None:
        """When to look again if no read starts now; None: start one (``poll_s`` since the last read, or the
        autopilot's fence id changed since, and the vehicle can be placed)."""
        if self.result is not None and self.params.poll_s <= 0.0:
            return now_s + IDLE_S
        next_read_s = self._ended_s + self.params.poll_s
        early = now_s < next_read_s
        if early and not self._id_changed():
            return min(next_read_s, now_s + IDLE_S)
        if self._reference() is None:
            return now_s + STEP_S
        if early:
            self._early_for = self._id_heard
            self.early += 1
        return None

    def _id_changed(self) -> bool:
        """A MISSION_CURRENT since the last read gave a fence id other than the one in service: the fence changed
        (an upload, a clear). Once per new id, so an autopilot whose MISSION_COUNT omits the id is read again only
        at the poll."""
        heard = self._id_heard
        return self.result is not None and heard is not None and heard not in (self._items_id, self._early_for)

    def _params_due(self, now_s: float) -> bool:
        """Ask for the fence parameters that are due; True once their read has ended (read whole or not)."""
        pr = self.param_read
        for name in pr.due(now_s):
            self._outbox.param_request_read(name)
        if pr.stage is ReadStage.RUNNING:
            return False
        if pr.stage is ReadStage.DONE:
            self.limits = fence_limits(self.params.profile, pr.values, switched_on=self.switched_on)
        else:
            self.limits = f"fence parameters not read ({pr.reason})"
        pr.rest()
        return True

    def _ended(self, now_s: float, *, failed: str | None = None) -> None:
        """A read ended with ``self._items`` as the fence, or its download failed (``failed`` says why): the next is
        due ``poll_s`` later; its result goes out when it is news."""
        self._ended_s = now_s
        self._id_heard = None
        if failed is not None:
            self.failures += 1
            if self.result is None:  # the first read: say that there is no fence to plan over (yet)
                self._tell(FenceArea(FenceOutcome.FAILED, f"download failed: {failed}"))
            return
        self.reads += 1
        limits = self.limits if isinstance(self.limits, FenceLimits) else None
        clearance = self._clearance_m()
        # What the result depends on: home only with a circle round it (ArduCopter moves home when it arms), the
        # margin's inset rather than C (a PARAM_SET of C that leaves the inset at 0 changes nothing).
        home = self.home if limits is not None and limits.home_radius_m is not None else None
        inputs = (self._items, limits, home, 0.0 if limits is None else limits.inset_m(clearance))
        r = self.result
        retry = r is not None and (r.outcome is FenceOutcome.NOT_USED or r.provisional)
        if inputs == self._inputs and not retry:
            return
        where = self._reference()
        if where is None:  # the reference went away (a reboot) between start and end: placed at the next read
            if self.result is None:
                self._tell(FenceArea(FenceOutcome.NOT_USED, "no global reference to place the fence"))
            return
        result = fence_area(self._items, *where, limits, home, clearance)
        if isinstance(self.limits, str) and result.outcome is FenceOutcome.USED:
            result = dataclasses.replace(result, note=f"{result.note}; {self.limits}: every uploaded zone used")
        if inputs == self._inputs and r is not None and _same(result, r):  # still not used, or provisional
            return
        self.changes += self._inputs is not None
        self._inputs = inputs
        self._tell(result)

    def _tell(self, result: FenceArea) -> None:
        self.result = result
        self._on_area(result)


_RUNNING = (FenceStage.COUNT, FenceStage.ITEMS)
#: The records besides the download's answers, each to its handler.
_OTHER_RECORDS: dict[type, Callable[[FenceReader, Any], None]] = {
    ParamValue: FenceReader.on_param,
    HomePosition: FenceReader.on_home,
    SysStatus: FenceReader.on_sys_status,
    MissionCurrent: FenceReader.on_mission_current,
}


def _same(a: FenceArea, b: FenceArea) -> bool:
    """The same outcome of the same fence: placed again about a reference that moved by centimetres, its polygons
    differ by as much, and that is no news."""
    return (a.outcome, a.note, a.provisional) == (b.outcome, b.note, b.provisional)
