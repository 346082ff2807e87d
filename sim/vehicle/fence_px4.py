"""The simulated PX4's fence transfers: one transfer state for every link and every mission type, as PX4's
``MavlinkMissionManager`` keeps it (``src/modules/mavlink/mavlink_mission.cpp``).

Where ArduPilot serves downloads without state, PX4 is IDLE, sending a list (a download, SENDLIST) or getting one
(an upload, GETLIST), with one partner (system, component):

- MISSION_REQUEST_LIST starts a download when IDLE, or again from the same partner (a download whose items were
  all sent counts as IDLE); otherwise it is ignored (a STATUSTEXT "Mission download request ignored, already
  active", no answer). Its MISSION_COUNT carries the fence plan's id (``opaque_id``), which MISSION_CURRENT's
  ``fence_id`` also gives at 1 Hz (``sim.vehicle.telemetry``).
- MISSION_REQUEST_INT from the partner during its download: the next item (or the last one again); any other
  sequence ends the download with MAV_MISSION_ERROR. From anyone else: a STATUSTEXT, no answer; when IDLE: ignored.
- MISSION_ACK from the partner ends its download.
- MISSION_COUNT starts an upload when IDLE (count 0 clears the fence at once, ACCEPTED); from the uploading
  partner before its first item it asks for item 0 again; anything else, during a download included, gets
  MAV_MISSION_ERROR.
- MISSION_ITEM_INT from the partner: out of turn ignored; after the last, the fence is kept, ACCEPTED (a repeat
  of the last item after the end gets ACCEPTED again).
- MISSION_CLEAR_ALL clears the fence when IDLE (ACCEPTED), else MAV_MISSION_ERROR.
- A transfer with nothing received for 5 s (``MAVLINK_MISSION_PROTOCOL_TIMEOUT_DEFAULT``) goes back to IDLE, here
  when the next mission message arrives.

Not modelled: PX4's re-requests after 250 ms (loopback loses nothing), its float MISSION_ITEM mode, missions and
rally points (UNSUPPORTED here).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.vehicle.missionwire import (
    FENCE,
    MAX_ITEMS,
    FenceItemRaw,
    MissionCountWithId,
    plan_id,
    send_ack,
    send_item,
    src_of,
)

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["PX4_FENCE_HANDLERS", "Px4Transfer"]

#: ``MAVLINK_MISSION_PROTOCOL_TIMEOUT_DEFAULT``: a transfer with nothing received for this long ends [s].
TIMEOUT_S = 5.0


class Px4State(enum.Enum):
    IDLE = "idle"
    SENDLIST = "sendlist"  # a download in progress
    GETLIST = "getlist"  # an upload in progress


@dataclass(slots=True)
class Px4Transfer:
    """PX4's one transfer: its state, partner, next sequence number, item count, last reception [s] and the items
    of an upload."""

    state: Px4State = Px4State.IDLE
    partner: tuple[int, int] = (0, 0)
    seq: int = 0
    count: int = 0
    last_rx_s: float = -math.inf
    items: list[FenceItemRaw] = field(default_factory=list)


def _transfer(v: VehicleEngine) -> Px4Transfer:
    """The transfer, back to IDLE when it has waited ``TIMEOUT_S``."""
    t = v.fence.px4
    if t.state is not Px4State.IDLE and v.t_s - t.last_rx_s > TIMEOUT_S:
        t.state = Px4State.IDLE
    return t


def _fence_only(fn: Any) -> Any:
    """Fence messages to ``fn``; another mission type's are refused (UNSUPPORTED) or, when they ask nothing, dropped."""

    def handler(v: VehicleEngine, msg: Any, link: int) -> None:
        mission_type = getattr(msg, "mission_type", 0)
        if mission_type == FENCE:
            fn(v, msg, link, _transfer(v))
        elif msg.get_type() in ("MISSION_COUNT", "MISSION_CLEAR_ALL"):
            send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_UNSUPPORTED, mission_type)
        elif msg.get_type() == "MISSION_REQUEST_LIST":
            v.emit(link, v.mav.mission_count_encode(*src_of(msg), 0, mission_type))

    return handler


def _request_list(v: VehicleEngine, msg: Any, link: int, t: Px4Transfer) -> None:
    if t.state is Px4State.SENDLIST and t.seq == t.count:  # every item sent: done, ack or not
        t.state = Px4State.IDLE
    if t.state is Px4State.IDLE or (t.state is Px4State.SENDLIST and t.partner == src_of(msg)):
        t.state, t.partner, t.seq, t.count, t.last_rx_s = Px4State.SENDLIST, src_of(msg), 0, len(v.fence.items), v.t_s
        v.emit(link, MissionCountWithId(t.partner, t.count, FENCE, plan_id(v.fence.items)))
    else:
        v.statustext(mavlink.MAV_SEVERITY_INFO, "Mission download request ignored, already active")


def _request_int(v: VehicleEngine, msg: Any, link: int, t: Px4Transfer) -> None:
    if src_of(msg) != t.partner:
        v.statustext(mavlink.MAV_SEVERITY_CRITICAL, "WPM: REJ. CMD: partner id mismatch")
        return
    if t.state is not Px4State.SENDLIST:
        if t.state is Px4State.GETLIST:
            v.statustext(mavlink.MAV_SEVERITY_CRITICAL, "WPM: REJ. CMD: Busy")
        return
    t.last_rx_s = v.t_s
    if msg.seq == t.seq and t.seq < t.count:
        t.seq += 1
    elif msg.seq != t.seq - 1 or msg.seq >= len(v.fence.items):
        t.state = Px4State.IDLE
        send_ack(v, link, t.partner, mavlink.MAV_MISSION_ERROR)
        return
    send_item(v, link, t.partner, msg.seq)


def _mission_ack(v: VehicleEngine, msg: Any, link: int, t: Px4Transfer) -> None:
    if t.state is Px4State.SENDLIST and src_of(msg) == t.partner:
        t.state = Px4State.IDLE


def _count(v: VehicleEngine, msg: Any, link: int, t: Px4Transfer) -> None:
    src = src_of(msg)
    if t.state is Px4State.GETLIST and src == t.partner and t.seq == 0:  # our request was lost: ask again
        t.last_rx_s = v.t_s
    elif t.state is not Px4State.IDLE:
        send_ack(v, link, src, mavlink.MAV_MISSION_ERROR)  # busy: a download, or another station's upload
        return
    elif msg.count > MAX_ITEMS:
        send_ack(v, link, src, mavlink.MAV_MISSION_NO_SPACE)
        return
    elif msg.count == 0:
        t.partner = src
        v.fence.replace_items([])
        send_ack(v, link, src, mavlink.MAV_MISSION_ACCEPTED)
        return
    else:
        t.state, t.partner, t.seq, t.count, t.items = Px4State.GETLIST, src, 0, int(msg.count), []
        t.last_rx_s = v.t_s
    v.emit(link, v.mav.mission_request_int_encode(*t.partner, t.seq, FENCE))


def _item_int(v: VehicleEngine, msg: Any, link: int, t: Px4Transfer) -> None:
    if src_of(msg) != t.partner:
        v.statustext(mavlink.MAV_SEVERITY_CRITICAL, "REJ. MIS ITEM: partner id mismatch")
        return
    if t.state is Px4State.IDLE:  # a repeat of the last item after the end (its ack lost), or none at all
        send_ack(
            v, link, t.partner, mavlink.MAV_MISSION_ACCEPTED if t.seq == msg.seq + 1 else mavlink.MAV_MISSION_ERROR
        )
        return
    if t.state is not Px4State.GETLIST:
        send_ack(v, link, t.partner, mavlink.MAV_MISSION_ERROR)
        return
    if msg.seq != t.seq:
        return
    t.items.append((int(msg.command), float(msg.param1), int(msg.x), int(msg.y)))
    t.seq, t.last_rx_s = t.seq + 1, v.t_s
    if t.seq < t.count:
        v.emit(link, v.mav.mission_request_int_encode(*t.partner, t.seq, FENCE))
        return
    t.state = Px4State.IDLE
    v.fence.replace_items(t.items)
    send_ack(v, link, t.partner, mavlink.MAV_MISSION_ACCEPTED)


def _clear_all(v: VehicleEngine, msg: Any, link: int, t: Px4Transfer) -> None:
    if t.state is not Px4State.IDLE:
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_ERROR)
        return
    v.fence.replace_items([])
    send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_ACCEPTED)


PX4_FENCE_HANDLERS = {
    mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_LIST: _fence_only(_request_list),
    mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_INT: _fence_only(_request_int),
    mavlink.MAVLINK_MSG_ID_MISSION_ACK: _fence_only(_mission_ack),
    mavlink.MAVLINK_MSG_ID_MISSION_COUNT: _fence_only(_count),
    mavlink.MAVLINK_MSG_ID_MISSION_ITEM_INT: _fence_only(_item_int),
    mavlink.MAVLINK_MSG_ID_MISSION_CLEAR_ALL: _fence_only(_clear_all),
}
