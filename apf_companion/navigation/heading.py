"""The heading commanded with the setpoints (``[autopilot] yaw = "travel"``, the PX4 default): the vehicle turns so
that its range sensor looks along the step it flies, so a sensor covering less than 360 degrees sees where the
vehicle goes. The sensor's direction is learnt from the ranges received (the look offset, body FRD:
apf_companion.perception.coverage): 0 for a forward sensor (the nose leads), pi for a rear one (the vehicle flies
backwards), 0 without readings or with all-round coverage.

PX4 holds its present heading when a setpoint's yaw is ignored (src/modules/mc_pos_control/PositionControl/
PositionControl.cpp ``_yaw_sp`` NAN -> FlightTaskOffboard keeps the current yaw); ArduCopter's GUIDED turns to
the direction of travel by itself (WP_YAW_BEHAVIOR, ArduCopter/autoyaw.cpp), so there the service sends none.
"""

from __future__ import annotations

import math

from apf_companion.navigation.model import FloatArray
from apf_companion.setpoint import Setpoint, SetpointKind, look_yaw, step_bearing, with_yaw

__all__ = ["MIN_YAW_STEP_M", "Heading"]

MIN_YAW_STEP_M = 0.05
"""A navigation step shorter than this keeps the last yaw [m]: the bearing of a few centimetres (the vehicle next
to its bacteria point, position noise) jumps about and would spin the vehicle."""


class Heading:
    """The yaw each setpoint carries: the bearing of the step being flown (NED, ``atan2(east, north)``) less the look
    offset (``setpoint.look_yaw``: the sensor's centre, not the nose, faces the step); a hold
    that wants a direction (a step refused towards a sector without recent ranges, ``StepTracker.known_direction``)
    already carries it; any other hold or short step keeps the last commanded yaw. Pre-stream holds and brakes
    carry none (the autopilot's own heading): before the takeover nothing was commanded, and a brake stops only."""

    def __init__(self) -> None:
        self.last_rad: float | None = None

    def reset(self) -> None:
        """Forget the last yaw (a new goal, a restarted leg): the pilot may have turned the vehicle meanwhile."""
        self.last_rad = None

    def apply(self, sp: Setpoint | None, pos_ned_m: FloatArray | None, look_offset_rad: float = 0.0) -> Setpoint | None:
        """``sp`` with its yaw (see the class); ``look_offset_rad``: where the range sensors look, body FRD [rad]."""
        if sp is None or sp.kind in (SetpointKind.PRESTREAM, SetpointKind.BRAKE):
            return sp
        if sp.yaw_rad is not None:
            self.last_rad = sp.yaw_rad
            return sp
        bearing = None if pos_ned_m is None else step_bearing(sp, pos_ned_m, MIN_YAW_STEP_M)
        if bearing is not None and math.isfinite(bearing):
            self.last_rad = look_yaw(bearing, look_offset_rad)
        return sp if self.last_rad is None else with_yaw(sp, self.last_rad)
