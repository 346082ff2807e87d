"""Whether the simulated ArduPilot's fence is switched on, and what SYS_STATUS says of it.

ArduPilot 4.6 (``libraries/AC_Fence/AC_Fence.cpp``) keeps the switch apart from its parameter: ``FENCE_ENABLE``
sets it at boot and whenever the parameter changes (``update``: "if someone changes the parameter we want to enable
or disable everything"), and MAV_CMD_DO_FENCE_ENABLE switches it at run time without changing the parameter
(``libraries/GCS_MAVLink/GCS_Fence.cpp``: param1 0 off, 1 on, 2 the floor only; else FAILED; "these changes are not
persisted"). SYS_STATUS reports it (``GCS.cpp`` ``update_sensor_status_flags``): the GEOFENCE bit is present when
a fence is configured (``present``: FENCE_TYPE's circle or altitude bits, or its polygon bit with items held), and
enabled when it is present, switched on and FENCE_ACTION is not 0 (report only: ``sys_status_enabled``). Not
modelled: FENCE_AUTOENABLE. Breaches and their actions: ``sim.vehicle.fencebreach``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

if TYPE_CHECKING:
    from sim.vehicle.params import ParamTable

__all__ = ["FenceSwitch", "geofence_flags"]

_CIRCLE_OR_ALT = 1 | 2 | 8  # AC_Fence.h: AC_FENCE_TYPE_ALT_MAX | CIRCLE | ALT_MIN
_POLYGON = 4


class FenceSwitch:
    """The run-time switch; ``follow`` it to the parameter each time it is read."""

    def __init__(self, param_on: bool) -> None:
        self.on = param_on
        self._param_on = param_on

    @classmethod
    def at_boot(cls, params: ParamTable) -> FenceSwitch:
        """The switch as FENCE_ENABLE sets it at boot (off on the PX4 profile, which has no such parameter)."""
        return cls("FENCE_ENABLE" in params and params["FENCE_ENABLE"] == 1.0)

    def follow(self, param_on: bool) -> bool:
        """The switch now: a change of FENCE_ENABLE sets it, as ArduPilot's ``update`` does."""
        if param_on != self._param_on:
            self._param_on = self.on = param_on
        return self.on

    def command(self, param1: float) -> int:
        """MAV_CMD_DO_FENCE_ENABLE's MAV_RESULT."""
        if param1 == 0.0 or param1 == 1.0:
            self.on = param1 == 1.0
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if param1 == 2.0:  # the floor only: there is no floor here
            return int(mavlink.MAV_RESULT_ACCEPTED)
        return int(mavlink.MAV_RESULT_FAILED)


def geofence_flags(fence_type: int, has_items: bool, on: bool, action: int) -> tuple[int, int]:
    """SYS_STATUS's GEOFENCE bit in (present, enabled)."""
    present = bool(fence_type & _CIRCLE_OR_ALT) or bool(fence_type & _POLYGON and has_items)
    bit = int(mavlink.MAV_SYS_STATUS_GEOFENCE)
    return (bit if present else 0), (bit if present and on and action != 0 else 0)
