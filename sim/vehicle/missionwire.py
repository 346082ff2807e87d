"""What the simulated autopilot's fence transfers send, on both profiles (``sim.vehicle.fence`` keeps ArduPilot's
rules, ``sim.vehicle.fence_px4`` PX4's): who asked, a MISSION_ACK, a fence item, and the item limit."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["FENCE", "MAX_ITEMS", "FenceItemRaw", "send_ack", "send_item", "src_of"]

FENCE = mavlink.MAV_MISSION_TYPE_FENCE
#: Fence items an upload may bring here, at most: this simulator's limit (ArduPilot's follows the board's fence
#: storage, PX4's its dataman); beyond it MISSION_ACK NO_SPACE, as both autopilots answer MISSION_COUNT.
MAX_ITEMS = 256

#: One stored fence item: command, param1 (vertex count or radius [m]), latitude, longitude [1e-7 deg].
FenceItemRaw = tuple[int, float, int, int]


def src_of(msg: Any) -> tuple[int, int]:
    """The sender (system, component): whom the answer goes to."""
    return msg.get_srcSystem(), msg.get_srcComponent()


def send_ack(v: VehicleEngine, link: int, to: tuple[int, int], result: int, mission_type: int = FENCE) -> None:
    """MISSION_ACK with ``result`` (MAV_MISSION_RESULT) to ``to`` on ``link``."""
    v.emit(link, v.mav.mission_ack_encode(*to, result, mission_type))


def send_item(v: VehicleEngine, link: int, to: tuple[int, int], seq: int, mission_type: int = FENCE) -> None:
    """MISSION_ITEM_INT ``seq`` of the fence held (``v.fence.items``; the caller checked ``seq``) to ``to``."""
    command, param1, lat, lon = v.fence.items[seq]
    v.emit(
        link,
        v.mav.mission_item_int_encode(
            *to, seq, mavlink.MAV_FRAME_GLOBAL, command, 0, 0, param1, 0.0, 0.0, 0.0, lat, lon, 0.0, mission_type
        ),
    )
