"""The simulated ArduPilot's run-time fence switch (ArduPilot 4.6, AC_Fence.cpp / GCS_Fence.cpp) and its SYS_STATUS
GEOFENCE bits (GCS.cpp update_sensor_status_flags), without sockets."""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.vehicle.fenceswitch import FenceSwitch, geofence_flags

GEOFENCE = int(mavlink.MAV_SYS_STATUS_GEOFENCE)


def test_the_switch_follows_the_parameter_and_the_command_without_changing_it() -> None:
    switch = FenceSwitch(False)
    assert switch.follow(False) is False
    assert switch.command(1.0) == mavlink.MAV_RESULT_ACCEPTED and switch.follow(False) is True  # not persisted
    assert switch.command(0.0) == mavlink.MAV_RESULT_ACCEPTED and switch.follow(False) is False
    assert switch.command(2.0) == mavlink.MAV_RESULT_ACCEPTED and switch.on is False  # the floor only
    assert switch.command(7.0) == mavlink.MAV_RESULT_FAILED
    switch.command(1.0)
    assert switch.follow(True) is True  # FENCE_ENABLE set to 1: on
    switch.command(0.0)
    assert switch.follow(True) is False  # the command since: off, the parameter unchanged
    assert switch.follow(False) is False and switch.follow(True) is True  # the parameter changed: it rules


def test_sys_status_says_configured_and_switched_on() -> None:
    assert geofence_flags(7, False, True, 1) == (GEOFENCE, GEOFENCE)  # circle and ceiling configured
    assert geofence_flags(7, False, False, 1) == (GEOFENCE, 0)  # configured, switched off
    assert geofence_flags(7, False, True, 0) == (GEOFENCE, 0)  # report only: not "enabled" (sys_status_enabled)
    assert geofence_flags(4, False, True, 1) == (0, 0)  # polygons configured, none uploaded: not present
    assert geofence_flags(4, True, True, 1) == (GEOFENCE, GEOFENCE)
