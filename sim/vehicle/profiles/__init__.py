"""Autopilot profiles: one class per autopilot, looked up by ``Autopilot`` in ``PROFILES``."""

from __future__ import annotations

from apf_companion.autopilot import Autopilot
from sim.vehicle.profiles.arducopter import ArduCopterProfile
from sim.vehicle.profiles.base import (
    AutopilotProfile,
    Behaviour,
    ProfileTexts,
    SetpointRule,
    param_int,
    replace_limits,
)
from sim.vehicle.profiles.px4 import Px4Profile

__all__ = [
    "PROFILES",
    "ArduCopterProfile",
    "AutopilotProfile",
    "Behaviour",
    "ProfileTexts",
    "Px4Profile",
    "SetpointRule",
    "param_int",
    "replace_limits",
]

PROFILES: dict[Autopilot, AutopilotProfile] = {
    Autopilot.ARDUPILOT: ArduCopterProfile(),
    Autopilot.PX4: Px4Profile(),
}
