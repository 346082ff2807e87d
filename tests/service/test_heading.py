"""The yaw sent with each setpoint under ``[autopilot] yaw = "travel"`` (apf_companion.navigation.heading)."""

from __future__ import annotations

import math

import numpy as np

from apf_companion.autopilot import MASK_POS_VEL, MASK_POS_VEL_YAW
from apf_companion.navigation.heading import MIN_YAW_STEP_M, Heading
from apf_companion.setpoint import SetpointKind, brake, hold, navigate, with_yaw

HERE = np.array([0.0, 0.0, -5.0])


def test_a_step_carries_its_bearing_and_a_hold_keeps_the_last_yaw() -> None:
    h = Heading()
    assert h.apply(hold(HERE), HERE) == hold(HERE)  # nothing commanded yet: the autopilot's own heading
    sp = h.apply(navigate(HERE, [-1.0, -1.0, -5.0], cruise_speed_m_s=1.0, dim=2), HERE)
    assert sp is not None and sp.type_mask == MASK_POS_VEL_YAW
    assert sp.yaw_rad is not None and math.isclose(sp.yaw_rad, math.atan2(-1.0, -1.0))
    held = h.apply(hold(HERE), HERE)
    assert held is not None and held.yaw_rad == sp.yaw_rad  # no turn back, no spin


def test_a_tiny_step_keeps_the_last_yaw() -> None:
    h = Heading()
    h.apply(navigate(HERE, [0.0, 1.0, -5.0], cruise_speed_m_s=1.0, dim=2), HERE)
    tiny = navigate(HERE, [-0.5 * MIN_YAW_STEP_M, 0.0, -5.0], cruise_speed_m_s=1.0, dim=2)
    sp = h.apply(tiny, HERE)
    assert sp is not None and sp.yaw_rad is not None and math.isclose(sp.yaw_rad, math.pi / 2)


def test_a_hold_that_wants_a_direction_sets_the_yaw_and_prestream_and_brake_carry_none() -> None:
    h = Heading()
    look = with_yaw(hold(HERE), 3.0 * math.pi / 2)  # wrapped to -pi/2
    assert look.yaw_rad is not None and math.isclose(look.yaw_rad, -math.pi / 2)
    assert h.apply(look, HERE) == look
    assert h.last_rad == look.yaw_rad
    pre = hold(HERE, SetpointKind.PRESTREAM)
    assert h.apply(pre, HERE) == pre and pre.type_mask == MASK_POS_VEL
    assert h.apply(brake(), HERE) == brake()
    h.reset()
    assert h.apply(hold(HERE), HERE) == hold(HERE)
