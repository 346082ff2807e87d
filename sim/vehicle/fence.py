"""The simulated autopilot's fence, served over the mission protocol (mission_type FENCE) as ArduPilot does
(``libraries/GCS_MAVLink/MissionItemProtocol.cpp``, ``handle_mission_request_list`` / ``handle_mission_request_int``):
MISSION_REQUEST_LIST is answered with MISSION_COUNT to the requester, MISSION_REQUEST_INT with that
MISSION_ITEM_INT, or with MISSION_ACK and the item's error (a sequence number past the end:
MAV_MISSION_INVALID_SEQUENCE, ``MissionItemProtocol_Fence::get_item``); the requester's closing MISSION_ACK needs
no answer.

The fence is the world file's flying area (``EngineConfig.fence``), as one inclusion polygon: every vertex a
MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION item with ``param1`` = the vertex count, latitude/longitude in 1e-7
degrees around home (``AC_PolyFence_loader`` stores and sends exactly this); a rectangle is its four corners.
Then its keep-out zones (``EngineConfig.fence_keepouts``), each an exclusion polygon
(MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION).
The fence can change while the vehicle flies (``VehicleEngine.set_fence``: what a ground station's upload
would leave), and every request is answered from the fence as it is then. Other mission types have no items here
(count 0), as before.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.planning import FlyingArea, KeepOuts, area_polygon
from sim.vehicle.geo import ne_to_latlon

if TYPE_CHECKING:
    from sim.vehicle.config import HomeConfig
    from sim.vehicle.engine import VehicleEngine

__all__ = ["FENCE_HANDLERS", "fence_items"]

_FENCE = mavlink.MAV_MISSION_TYPE_FENCE


def fence_items(area: FlyingArea | None, keepouts: KeepOuts, home: HomeConfig) -> list[tuple[int, int, int, int]]:
    """(command, vertex count, latitude, longitude [1e-7 deg]) of each fence item: the area as one inclusion
    polygon, then each keep-out zone as an exclusion polygon."""
    zones: list[tuple[int, list[tuple[float, float]]]] = []
    if area is not None:
        zones.append((mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, list(area_polygon(area))))
    zones += [(mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION, list(zone)) for zone in keepouts]
    out = []
    for command, vertices in zones:
        for n, e in vertices:
            lat, lon = ne_to_latlon(home, n, e)
            out.append((command, len(vertices), round(lat * 1e7), round(lon * 1e7)))
    return out


def _items(v: VehicleEngine) -> list[tuple[int, int, int, int]]:
    return fence_items(*v.fence_zones, v.cfg.home)


def _on_mission_request_list(v: VehicleEngine, msg: Any, link: int) -> None:
    mission_type = getattr(msg, "mission_type", 0)
    count = len(_items(v)) if mission_type == _FENCE else 0
    v.emit(link, v.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), count, mission_type))


def _on_mission_request_int(v: VehicleEngine, msg: Any, link: int) -> None:
    mission_type = getattr(msg, "mission_type", 0)
    items = _items(v) if mission_type == _FENCE else []
    src = (msg.get_srcSystem(), msg.get_srcComponent())
    if not 0 <= msg.seq < len(items):
        v.emit(link, v.mav.mission_ack_encode(*src, mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type))
        return
    command, count, lat, lon = items[msg.seq]
    v.emit(
        link,
        v.mav.mission_item_int_encode(
            *src, msg.seq, mavlink.MAV_FRAME_GLOBAL, command, 0, 0, float(count), 0.0, 0.0, 0.0, lat, lon, 0.0,
            mission_type,
        ),
    )  # fmt: skip


FENCE_HANDLERS = {
    mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_LIST: _on_mission_request_list,
    mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_INT: _on_mission_request_int,
}
