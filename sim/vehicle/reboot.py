"""MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN on the ArduPilot profile: the rules for accepting it, and the reboot.

``GCS_Common.cpp`` ``handle_preflight_reboot``: refused (FAILED) while armed unless param6 (COMMAND_INT ``y``) is
the magic 20190226; param1 must be 1 (reboot) or 3 (reboot to the bootloader), else UNSUPPORTED; the ACK goes out
before the reboot. On SITL the "bootloader" variant restarts the firmware like 1 (there is no bootloader), and so
does the simulator.

After the ACK the autopilot is down (no messages in or out) for ``DOWN_S``, then boots: for ``BOOT_S`` it sends
only HEARTBEAT with MAV_STATE_BOOT (``GCS_MAVLINK_Copter::vehicle_system_status``: BOOT until
``ap.initialised``) and ignores input. Then it runs again as after power-up: ``time_boot_ms`` from 0, mode
STABILIZE, no GUIDED target, message intervals back to their defaults, the parameters as stored (a PRX1_TYPE set
before the reboot now takes effect). DOWN_S and BOOT_S are assumptions (not measured on SITL).
"""

from __future__ import annotations

import enum
import math
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.vehicle.guided import GuidedState
from sim.vehicle.proximity import Proximity
from sim.vehicle.startup import EkfStartup

if TYPE_CHECKING:
    from sim.vehicle.commands import Command
    from sim.vehicle.engine import VehicleEngine

__all__ = ["BOOT_S", "DOWN_S", "BootPhase", "BootState", "handle_reboot", "reboot_engine"]

FORCE_REBOOT_MAGIC = 20190226  # GCS_Common.cpp magic_force_reboot_value (COMMAND_INT y / param6)
DOWN_S = 0.5  # after the ACK, nothing is sent or read [s] (assumed)
BOOT_S = 1.0  # then HEARTBEAT with MAV_STATE_BOOT only [s] (assumed)
HEARTBEAT_PERIOD_S = 1.0


class BootPhase(enum.Enum):
    RUNNING = "running"
    DOWN = "down"
    BOOTING = "booting"


class BootState:
    """When the autopilot last (re)booted, and whether it is running now."""

    def __init__(self) -> None:
        self.boot_t_s = 0.0  # simulated time of the last boot (time_boot_ms counts from here)
        self.down_until_s = -math.inf
        self.booting_until_s = -math.inf
        self.reboots = 0
        self._next_heartbeat_s = 0.0

    def phase(self, t_s: float) -> BootPhase:
        if t_s < self.down_until_s:
            return BootPhase.DOWN
        if t_s < self.booting_until_s:
            return BootPhase.BOOTING
        return BootPhase.RUNNING

    def start(self, t_s: float) -> None:
        """The reboot begins now: down, then booting; time since boot restarts when the firmware starts."""
        self.reboots += 1
        self.down_until_s = t_s + DOWN_S
        self.booting_until_s = self.down_until_s + BOOT_S
        self.boot_t_s = self.down_until_s
        self._next_heartbeat_s = self.down_until_s

    def tick_booting(self, v: VehicleEngine) -> None:
        """While booting: HEARTBEAT (MAV_STATE_BOOT) at 1 Hz on every link, nothing else."""
        if v.t_s < self._next_heartbeat_s - 1e-9:
            return
        self._next_heartbeat_s = v.t_s + HEARTBEAT_PERIOD_S
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        kind, autopilot = mavlink.MAV_TYPE_QUADROTOR, v.profile_rules.mav_autopilot
        v.emit(None, v.mav.heartbeat_encode(kind, autopilot, base_mode, v.custom_mode, mavlink.MAV_STATE_BOOT))


def handle_reboot(v: VehicleEngine, c: Command) -> int | None:
    """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: ACK then reboot (None: already answered), or the refusal's result."""
    if not v.profile_rules.supports_reboot:
        return int(mavlink.MAV_RESULT_UNSUPPORTED)
    if v.armed and c.p[5] != FORCE_REBOOT_MAGIC:
        return int(mavlink.MAV_RESULT_FAILED)  # "refuse reboot when armed"
    if c.p[0] not in (1.0, 3.0):
        return int(mavlink.MAV_RESULT_UNSUPPORTED)  # 1 reboot, 3 reboot to the bootloader
    v.ack(c.link, c.msg, c.command, mavlink.MAV_RESULT_ACCEPTED)
    v.reboot()
    return None


def reboot_engine(v: VehicleEngine) -> None:
    """Restart the autopilot of ``v`` now, as after power-up (module docstring); the vehicle stays where it is."""
    if v.armed:
        v.armed = False  # a forced reboot stops the motors
        v.landed_since_s = None
    v.custom_mode = v.profile_rules.initial_mode(False)  # ArduCopter boots in STABILIZE
    v.takeoff_alt_m = None
    v.rtl_phase = 0
    v.failsafe = False
    v.offboard_fallback = False
    v.guided = GuidedState()
    v.hold_pos_ned_m = v.state.pos_ned_m.copy()
    v.boot.start(v.t_s)
    v.telemetry.reset(v.boot.boot_t_s)
    # The EKF starts again: no origin until the profile's delay after this boot (fast_start: at once, as at power-up).
    v.startup = EkfStartup(skip=v.cfg.fast_start, boot_t_s=v.boot.boot_t_s)
    v.proximity = Proximity.at_boot(v.params)
    v.ranging.next_scan_t = v.boot.booting_until_s
