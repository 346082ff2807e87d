"""The simulated autopilot's fence over the mission protocol (mission_type FENCE), served and uploaded as ArduPilot
does it (``libraries/GCS_MAVLink/MissionItemProtocol.cpp``).

Download (``handle_mission_request_list`` / ``handle_mission_request_int``): MISSION_REQUEST_LIST is answered
with MISSION_COUNT to the requester, MISSION_REQUEST_INT with that MISSION_ITEM_INT, or with MISSION_ACK and
the item's error (a sequence number past the end: MAV_MISSION_INVALID_SEQUENCE,
``MissionItemProtocol_Fence::get_item``); the requester's closing MISSION_ACK needs no answer.

Upload (``handle_mission_count``, ``handle_mission_item``, ``transfer_is_complete``): MISSION_COUNT starts it
(count 0 clears the fence at once, as MISSION_CLEAR_ALL does: ``handle_mission_clear_all``); the vehicle asks
for each item in turn (MISSION_REQUEST on the ArduPilot profile, as ``queued_request_send`` does;
MISSION_REQUEST_INT on PX4's) and, after the last, keeps the new fence and sends MISSION_ACK ACCEPTED. While one
ground station uploads, another's MISSION_COUNT and every download request get MISSION_ACK DENIED
(``cancel_upload``, "someone is uploading a mission; reject fetching of points"), its MISSION_CLEAR_ALL DENIED
and ERROR. An item out of turn gets INVALID_SEQUENCE; one from another system DENIED; a command that is no fence item
UNSUPPORTED, which ends the upload. An upload without an item for 8 s (``upload_timeout_ms``) is cancelled
(MISSION_ACK OPERATION_CANCELLED to the uploader), here when the next fence message arrives. Not modelled:
re-requesting an item after 1 s (loopback loses nothing) and checking the new fence's geometry. The PX4 profile
keeps PX4's one transfer state instead (``sim.vehicle.fence_px4``).

The fence at start is the world file's flying area (``EngineConfig.fence``), as one inclusion polygon: every
vertex a MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION item with ``param1`` = the vertex count, latitude/longitude
in 1e-7 degrees around home (``AC_PolyFence_loader`` stores and sends exactly this); a rectangle is its four
corners. Then its keep-out zones (``EngineConfig.fence_keepouts``), each an exclusion polygon
(MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION). An upload replaces it with the items as sent (circles too), and a
test may replace it directly (``FenceStore.set_zones``). Other mission types have no items here (count 0) and
take no uploads (UNSUPPORTED).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from apf_companion.planning import FlyingArea, KeepOuts, area_polygon
from sim.vehicle.fence_px4 import PX4_FENCE_HANDLERS, Px4Transfer
from sim.vehicle.fencebreach import FenceGuard
from sim.vehicle.fenceswitch import FenceSwitch
from sim.vehicle.geo import ne_to_latlon
from sim.vehicle.missionwire import FENCE, MAX_ITEMS, FenceItemRaw, send_ack, send_item, src_of

if TYPE_CHECKING:
    from sim.vehicle.config import HomeConfig
    from sim.vehicle.engine import VehicleEngine

__all__ = ["FENCE_HANDLERS", "FenceItemRaw", "FenceStore", "FenceUpload", "fence_items"]

#: ``MissionItemProtocol::upload_timeout_ms``: an upload without an item for this long is cancelled [s].
UPLOAD_TIMEOUT_S = 8.0
_FENCE_COMMANDS = frozenset(
    {
        mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT,
    }
)


@dataclass(slots=True)
class FenceUpload:
    """An upload in progress: who sends it (system, component), on which link, how many items, those received."""

    src: tuple[int, int]
    link: int
    count: int
    last_rx_s: float
    items: list[FenceItemRaw] = field(default_factory=list)


@dataclass(slots=True)
class FenceStore:
    """The fence the vehicle holds (items about ``home``), the upload in progress, if any, and ``uploads``, the
    completed uploads."""

    home: HomeConfig
    items: list[FenceItemRaw]
    #: ArduPilot's run-time switch (FENCE_ENABLE at boot, MAV_CMD_DO_FENCE_ENABLE; sim.vehicle.fenceswitch).
    switch: FenceSwitch = field(default_factory=lambda: FenceSwitch(False))
    upload: FenceUpload | None = None  # ArduPilot's upload in progress
    px4: Px4Transfer = field(default_factory=Px4Transfer)  # PX4's one transfer (sim.vehicle.fence_px4)
    uploads: int = 0
    #: What is breached, and the count of breaches (sim.vehicle.fencebreach).
    guard: FenceGuard = field(default_factory=FenceGuard)

    @classmethod
    def of_zones(cls, area: FlyingArea | None, keepouts: KeepOuts, home: HomeConfig, switch: FenceSwitch) -> FenceStore:
        return cls(home, fence_items(area, keepouts, home), switch)

    def replace_items(self, items: list[FenceItemRaw]) -> None:
        """A completed upload's items (none: cleared) become the fence held."""
        self.items = items
        self.uploads += 1

    def set_zones(self, area: FlyingArea | None, keepouts: KeepOuts = ()) -> None:
        """A new fence (``area`` as one inclusion polygon, ``keepouts`` as exclusion polygons), as a ground
        station's upload would leave it; the next fence request is answered from it."""
        self.items = fence_items(area, keepouts, self.home)


def fence_items(area: FlyingArea | None, keepouts: KeepOuts, home: HomeConfig) -> list[FenceItemRaw]:
    """The fence items of ``area`` (one inclusion polygon) and ``keepouts`` (one exclusion polygon each)."""
    zones: list[tuple[int, list[tuple[float, float]]]] = []
    if area is not None:
        zones.append((mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, list(area_polygon(area))))
    zones += [(mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION, list(zone)) for zone in keepouts]
    out: list[FenceItemRaw] = []
    for command, vertices in zones:
        for n, e in vertices:
            lat, lon = ne_to_latlon(home, n, e)
            out.append((command, float(len(vertices)), round(lat * 1e7), round(lon * 1e7)))
    return out


def _receiving(v: VehicleEngine) -> FenceUpload | None:
    """The upload in progress, after cancelling one that has waited ``UPLOAD_TIMEOUT_S`` for an item."""
    up = v.fence.upload
    if up is not None and v.t_s - up.last_rx_s > UPLOAD_TIMEOUT_S:
        send_ack(v, up.link, up.src, mavlink.MAV_MISSION_OPERATION_CANCELLED)
        v.fence.upload = up = None
    return up


def _request(v: VehicleEngine, up: FenceUpload, seq: int) -> None:
    if v.profile is Autopilot.ARDUPILOT:
        v.emit(up.link, v.mav.mission_request_encode(*up.src, seq, FENCE))
    else:
        v.emit(up.link, v.mav.mission_request_int_encode(*up.src, seq, FENCE))


def _served_count(v: VehicleEngine, msg: Any, link: int) -> int | None:
    """The items a download request of ``msg``'s mission type sees (other types have none here), or None when it is
    refused: an upload is in progress (MISSION_ACK DENIED, ``handle_mission_request_list`` / ``_int``)."""
    mission_type = getattr(msg, "mission_type", 0)
    if mission_type == FENCE and _receiving(v) is not None:
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_DENIED)
        return None
    return len(v.fence.items) if mission_type == FENCE else 0


def _on_mission_request_list(v: VehicleEngine, msg: Any, link: int) -> None:
    count = _served_count(v, msg, link)
    if count is not None:
        v.emit(link, v.mav.mission_count_encode(*src_of(msg), count, getattr(msg, "mission_type", 0)))


def _on_mission_request_int(v: VehicleEngine, msg: Any, link: int) -> None:
    count = _served_count(v, msg, link)
    mission_type = getattr(msg, "mission_type", 0)
    if count is None:
        return
    if not 0 <= msg.seq < count:
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type)
        return
    send_item(v, link, src_of(msg), msg.seq, mission_type)


def _on_mission_count(v: VehicleEngine, msg: Any, link: int) -> None:
    mission_type = getattr(msg, "mission_type", 0)
    src = src_of(msg)
    if mission_type != FENCE:
        send_ack(v, link, src, mavlink.MAV_MISSION_UNSUPPORTED, mission_type)  # no mission, no rally points here
        return
    up = _receiving(v)
    if up is not None and up.src != src:
        send_ack(v, link, src, mavlink.MAV_MISSION_DENIED)
        return
    if msg.count > MAX_ITEMS:
        send_ack(v, link, src, mavlink.MAV_MISSION_NO_SPACE)
        return
    if msg.count == 0:
        v.fence.upload = None
        v.fence.replace_items([])
        send_ack(v, link, src, mavlink.MAV_MISSION_ACCEPTED)
        return
    v.fence.upload = up = FenceUpload(src=src, link=link, count=int(msg.count), last_rx_s=v.t_s)
    _request(v, up, 0)


def _on_mission_item_int(v: VehicleEngine, msg: Any, link: int) -> None:
    up = _receiving(v) if getattr(msg, "mission_type", 0) == FENCE else None
    if up is None:
        return
    if msg.seq != len(up.items):
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_INVALID_SEQUENCE)
        return
    if src_of(msg) != up.src:
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_DENIED)
        return
    if msg.command not in _FENCE_COMMANDS:
        send_ack(v, link, up.src, mavlink.MAV_MISSION_UNSUPPORTED)
        v.fence.upload = None
        return
    up.items.append((int(msg.command), float(msg.param1), int(msg.x), int(msg.y)))
    up.last_rx_s = v.t_s
    if len(up.items) < up.count:
        _request(v, up, len(up.items))
        return
    v.fence.upload = None
    v.fence.replace_items(up.items)
    send_ack(v, link, up.src, mavlink.MAV_MISSION_ACCEPTED)


def _on_mission_clear_all(v: VehicleEngine, msg: Any, link: int) -> None:
    """``handle_mission_clear_all``: another ground station's upload in progress refuses it (DENIED from
    ``cancel_upload``, then ERROR); else the uploader's own upload is cancelled, the fence cleared, ACCEPTED."""
    mission_type = getattr(msg, "mission_type", 0)
    if mission_type != FENCE:
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_UNSUPPORTED, mission_type)
        return
    up = _receiving(v)
    if up is not None and up.src != src_of(msg):
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_DENIED)
        send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_ERROR)
        return
    v.fence.upload = None
    v.fence.replace_items([])
    send_ack(v, link, src_of(msg), mavlink.MAV_MISSION_ACCEPTED)


_ARDUPILOT_HANDLERS = {
    mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_LIST: _on_mission_request_list,
    mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_INT: _on_mission_request_int,
    mavlink.MAVLINK_MSG_ID_MISSION_COUNT: _on_mission_count,
    mavlink.MAVLINK_MSG_ID_MISSION_ITEM_INT: _on_mission_item_int,
    mavlink.MAVLINK_MSG_ID_MISSION_CLEAR_ALL: _on_mission_clear_all,
}


def _by_profile(msg_id: int) -> Callable[[VehicleEngine, Any, int], None]:
    """The handler of ``msg_id`` for the vehicle's profile: PX4's one transfer state (``sim.vehicle.fence_px4``) or
    ArduPilot's (this module); a profile without one drops the message."""
    ardupilot, px4 = _ARDUPILOT_HANDLERS.get(msg_id), PX4_FENCE_HANDLERS.get(msg_id)

    def handler(v: VehicleEngine, msg: Any, link: int) -> None:
        fn = px4 if v.profile is Autopilot.PX4 else ardupilot
        if fn is not None:
            fn(v, msg, link)

    return handler


FENCE_HANDLERS = {msg_id: _by_profile(msg_id) for msg_id in {*_ARDUPILOT_HANDLERS, *PX4_FENCE_HANDLERS}}
