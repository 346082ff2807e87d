"""What the simulated autopilot's fence transfers send, on both profiles (``sim.vehicle.fence`` keeps ArduPilot's
rules, ``sim.vehicle.fence_px4`` PX4's): who asked, a MISSION_ACK, a fence item, and the item limit."""

from __future__ import annotations

import struct
import zlib
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = [
    "FENCE",
    "MAX_ITEMS",
    "FenceItemRaw",
    "MissionCountWithId",
    "MissionCurrentWithIds",
    "plan_id",
    "send_ack",
    "send_item",
    "src_of",
]

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


def plan_id(items: list[FenceItemRaw]) -> int:
    """The fence plan's id as PX4 gives it: a CRC32 over its items, 0 for no fence (``mavlink_mission.cpp`` keeps
    ``_crc32[MAV_MISSION_TYPE_FENCE]``, accumulated over each item as it is uploaded; here over the items as
    stored, so the same fence has the same id)."""
    return zlib.crc32(b"".join(struct.pack("<ifii", *item) for item in items))


# MAVLink's plan ids (mavlink/mavlink#2012) are uint32 extensions that pymavlink 2.4.50's dialect lacks. These two
# messages pack them after the fields it knows, at their offsets in common.xml; the CRC's extra byte covers only
# the base fields, so the frames are what an autopilot with the newer dialect sends.


class MissionCurrentWithIds(mavlink.MAVLink_mission_current_message):  # type: ignore[misc]  # untyped base
    """MISSION_CURRENT with ``mission_id``, ``fence_id`` and ``rally_points_id`` (payload bytes 6-17)."""

    def __init__(self, seq: int, total: int, mission_state: int, mission_mode: int, fence_id: int) -> None:
        super().__init__(seq, total, mission_state, mission_mode)
        self.fence_id = fence_id

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        base = self.unpacker.pack(self.seq, self.total, self.mission_state, self.mission_mode)
        return bytes(self._pack(mav, self.crc_extra, base + struct.pack("<III", 0, self.fence_id, 0), force_mavlink1))


class MissionCountWithId(mavlink.MAVLink_mission_count_message):  # type: ignore[misc]  # untyped base
    """MISSION_COUNT with ``opaque_id`` (payload bytes 5-8): the id of the plan being sent."""

    def __init__(self, target: tuple[int, int], count: int, mission_type: int, opaque_id: int) -> None:
        super().__init__(*target, count, mission_type)
        self.opaque_id = opaque_id

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        base = self.unpacker.pack(self.count, self.target_system, self.target_component, self.mission_type)
        return bytes(self._pack(mav, self.crc_extra, base + struct.pack("<I", self.opaque_id), force_mavlink1))
