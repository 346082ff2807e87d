"""Autopilot facts a companion must get right: mode numbers, PX4 custom_mode layout, type_mask constants.

Local NED frame throughout (MAV_FRAME_LOCAL_NED = 1): x north, y east, z down, metres, relative to the EKF origin.
Sources: ArduCopter ``mode.h`` (mode numbers), PX4 ``px4_custom_mode.h`` (main mode in bits 16-23 and sub mode in
bits 24-31 of HEARTBEAT.custom_mode), MAVLink common.xml POSITION_TARGET_TYPEMASK (bits are *ignore* flags).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = [
    "ACC_IGNORE",
    "COMP_AUTOPILOT",
    "COMP_OBSTACLE_AVOIDANCE",
    "COMP_ONBOARD_COMPUTER",
    "COMP_PATHPLANNER",
    "MASK_ACCELERATION",
    "MASK_POSITION",
    "MASK_POSITION_YAW",
    "MASK_POS_VEL",
    "MASK_POS_VEL_ACCEL",
    "MASK_POS_VEL_YAW",
    "MASK_VELOCITY",
    "POS_IGNORE",
    "PX4_HOLD",
    "PX4_LAND",
    "PX4_OFFBOARD",
    "PX4_POSCTL",
    "PX4_TAKEOFF",
    "VEL_IGNORE",
    "YAW_ALL_IGNORE",
    "Autopilot",
    "CopterMode",
    "Px4AutoSubMode",
    "Px4MainMode",
    "Px4Mode",
    "TypeMask",
    "guided_mode_name",
]


class Autopilot(enum.Enum):
    """Which autopilot firmware the companion talks to; each has its own mode rules."""

    ARDUPILOT = "ardupilot"
    PX4 = "px4"


def guided_mode_name(profile: Autopilot) -> str:
    """The name of the mode in which ``profile`` flies a companion's setpoints, as its ground stations show it:
    ArduCopter GUIDED (``mode.h``), PX4 OFFBOARD (``px4_custom_mode.h``)."""
    return "GUIDED" if profile is Autopilot.ARDUPILOT else "OFFBOARD"


class CopterMode(enum.IntEnum):
    """ArduCopter flight modes (HEARTBEAT.custom_mode; DO_SET_MODE param2)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    CIRCLE = 7
    LAND = 9
    DRIFT = 11
    SPORT = 13
    FLIP = 14
    AUTOTUNE = 15
    POSHOLD = 16
    BRAKE = 17
    THROW = 18
    AVOID_ADSB = 19
    GUIDED_NOGPS = 20
    SMART_RTL = 21


class Px4MainMode(enum.IntEnum):
    """PX4 main modes (custom_mode bits 16-23; DO_SET_MODE param2)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class Px4AutoSubMode(enum.IntEnum):
    """PX4 AUTO sub modes (custom_mode bits 24-31; DO_SET_MODE param3)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    FOLLOW_TARGET = 8
    PRECLAND = 9


@dataclass(frozen=True, slots=True)
class Px4Mode:
    """A PX4 mode as the (main, sub) pair packed into HEARTBEAT.custom_mode."""

    main: int
    sub: int = 0

    def to_custom_mode(self) -> int:
        return ((self.main & 0xFF) << 16) | ((self.sub & 0xFF) << 24)

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> Px4Mode:
        return cls(main=(custom_mode >> 16) & 0xFF, sub=(custom_mode >> 24) & 0xFF)


PX4_OFFBOARD = Px4Mode(Px4MainMode.OFFBOARD)
PX4_HOLD = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.LOITER)
PX4_TAKEOFF = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.TAKEOFF)
PX4_LAND = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.LAND)
PX4_POSCTL = Px4Mode(Px4MainMode.POSCTL)


class TypeMask(enum.IntFlag):
    """POSITION_TARGET_TYPEMASK: each set bit tells the autopilot to IGNORE that field (pymavlink's dialect
    constants, common.xml)."""

    X_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    Y_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    Z_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
    VX_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    VY_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    VZ_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
    AX_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    AY_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    AZ_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    FORCE_SET = mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET
    YAW_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
    YAW_RATE_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE


POS_IGNORE = TypeMask.X_IGNORE | TypeMask.Y_IGNORE | TypeMask.Z_IGNORE
VEL_IGNORE = TypeMask.VX_IGNORE | TypeMask.VY_IGNORE | TypeMask.VZ_IGNORE
ACC_IGNORE = TypeMask.AX_IGNORE | TypeMask.AY_IGNORE | TypeMask.AZ_IGNORE
YAW_ALL_IGNORE = TypeMask.YAW_IGNORE | TypeMask.YAW_RATE_IGNORE

# The combinations of the ArduCopter wiki ("copter-commands-in-guided-mode"), by name.
MASK_POSITION = int(VEL_IGNORE | ACC_IGNORE | YAW_ALL_IGNORE)  # 0x0DF8 = 3576
MASK_VELOCITY = int(POS_IGNORE | ACC_IGNORE | YAW_ALL_IGNORE)  # 0x0DC7 = 3527
MASK_ACCELERATION = int(POS_IGNORE | VEL_IGNORE | YAW_ALL_IGNORE)  # 0x0C3F = 3135
MASK_POS_VEL = int(ACC_IGNORE | YAW_ALL_IGNORE)  # 0x0DC0 = 3520
MASK_POS_VEL_ACCEL = int(YAW_ALL_IGNORE)  # 0x0C00 = 3072
MASK_POS_VEL_YAW = int(ACC_IGNORE | TypeMask.YAW_RATE_IGNORE)  # 0x09C0 = 2496
MASK_POSITION_YAW = int(VEL_IGNORE | ACC_IGNORE | TypeMask.YAW_RATE_IGNORE)  # 0x09F8 = 2552

# MAV_COMPONENT ids a companion may use; never the GCS's (MISSIONPLANNER = 190).
COMP_ONBOARD_COMPUTER = 191
COMP_PATHPLANNER = 195
COMP_OBSTACLE_AVOIDANCE = 196
COMP_AUTOPILOT = 1
