"""The pure takeover controller on an injected clock: every transition, resend, timeout and goal change."""

from __future__ import annotations

import dataclasses

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import Autopilot
from apf_companion.takeover import (
    COMMAND_RETRY_S,
    HARD_TIMEOUT_FACTOR,
    HEARTBEATS_TO_FAIL,
    Action,
    ActionKind,
    Phase,
    TakeoverController,
    TakeoverInputs,
    TakeoverParams,
)

ROUTE = object()  # the goal, compared by identity
SET_MODE = m.MAV_CMD_DO_SET_MODE
ARM = m.MAV_CMD_COMPONENT_ARM_DISARM
TAKEOFF = m.MAV_CMD_NAV_TAKEOFF
GROUND = TakeoverInputs(navigating=True, engaged=False, route=ROUTE, mode_ok=False, armed=False, down_m=0.0)


def phase(c: TakeoverController) -> Phase:
    """The phase, read through a call (mypy would keep an attribute narrowed across steps)."""
    return c.phase


def kinds(actions: list[Action]) -> list[ActionKind]:
    return [a.kind for a in actions]


def ctl(**kw: object) -> TakeoverController:
    return TakeoverController(dataclasses.replace(TakeoverParams(), **kw))  # type: ignore[arg-type]


def test_nothing_without_a_goal_to_take_over_for() -> None:
    c = ctl()
    assert c.step(0.0, dataclasses.replace(GROUND, route=None)) == []
    assert c.step(0.0, dataclasses.replace(GROUND, navigating=False)) == []
    assert c.step(0.0, dataclasses.replace(GROUND, engaged=True)) == []
    assert ctl(enabled=False).step(0.0, GROUND) == []
    assert phase(c) is Phase.IDLE and c.poll_interval_s == pytest.approx(0.05)


def test_ardupilot_guided_without_arming_resends_until_confirmed() -> None:
    c = ctl()
    assert kinds(c.step(0.0, GROUND)) == [ActionKind.STARTED, ActionKind.SET_MODE]
    assert phase(c) is Phase.MODE and c.poll_interval_s == pytest.approx(0.02)
    assert c.step(0.5, GROUND) == []  # not yet time to resend
    assert kinds(c.step(COMMAND_RETRY_S, GROUND)) == [ActionKind.SET_MODE]
    assert kinds(c.step(1.2, dataclasses.replace(GROUND, mode_ok=True))) == [ActionKind.DONE]
    assert phase(c) is Phase.IDLE


def test_mode_not_confirmed_in_time_fails_and_drops_the_goal() -> None:
    c = ctl(mode_timeout_s=2.0)
    c.step(0.0, GROUND)
    c.step(1.0, GROUND)
    c.step(2.0, GROUND)
    out = c.step(2.01, GROUND)
    assert kinds(out) == [ActionKind.FAILED]
    assert out[0].reason == "GUIDED not confirmed within 2.0 s"
    assert phase(c) is Phase.IDLE


def test_a_replaced_goal_abandons_the_takeover_without_failing_then_the_new_goal_starts_one() -> None:
    """Not a failure (the log said ``takeover.failed ... goal replaced`` at WARNING): the new goal is kept and gets
    its own takeover at the next step."""
    c = ctl()
    c.step(0.0, GROUND)
    new_goal = dataclasses.replace(GROUND, route=object())
    out = c.step(0.1, new_goal)
    assert kinds(out) == [ActionKind.ABANDONED] and out[0].reason == "GUIDED: goal replaced"
    assert phase(c) is Phase.IDLE
    assert ActionKind.STARTED in kinds(c.step(0.2, new_goal))
    out = c.step(0.3, dataclasses.replace(GROUND, route=None))
    assert kinds(out)[-1] is ActionKind.ABANDONED and out[-1].reason.endswith("goal dropped")


def test_ardupilot_arm_and_takeoff_in_order_with_the_navigator_suspended() -> None:
    c = ctl(arm=True, takeoff_alt_m=5.0)
    # ArduCopter takes off only in GUIDED: switch first.
    assert kinds(c.step(0.0, GROUND)) == [ActionKind.STARTED, ActionKind.SUSPEND, ActionKind.SET_MODE]
    assert phase(c) is Phase.MODE_BEFORE_ARM
    guided = dataclasses.replace(GROUND, mode_ok=True)
    assert kinds(c.step(0.1, guided)) == [ActionKind.ARM]
    assert phase(c) is Phase.ARMING
    armed = dataclasses.replace(guided, armed=True)
    out = c.step(0.2, armed)
    assert kinds(out) == [ActionKind.TAKEOFF] and out[0].value == 5.0  # param7: height above home
    assert phase(c) is Phase.TAKEOFF
    assert c.step(0.3, dataclasses.replace(armed, down_m=-4.0)) == []  # 4 m < 90 % of 5 m
    # climbing: no second NAV_TAKEOFF (ArduCopter would refuse it: not landed)
    assert c.step(0.2 + COMMAND_RETRY_S, dataclasses.replace(armed, down_m=-4.0)) == []
    out = c.step(1.5, dataclasses.replace(armed, down_m=-4.6))
    assert kinds(out) == [ActionKind.AIRBORNE, ActionKind.RESUME, ActionKind.DONE]
    assert out[0].value == -5.0


def test_an_accepted_arm_ack_confirms_arming_before_the_heartbeat_does() -> None:
    """Both autopilots ACK arm ACCEPTED only when armed: NAV_TAKEOFF goes out on the ACK, without waiting up to a
    HEARTBEAT period (more on a lossy link) while ArduCopter's DISARM_DELAY runs. An ACK from before the phase
    (an earlier takeover's) does not count."""
    c = ctl(arm=True, takeoff_alt_m=5.0)
    guided = dataclasses.replace(GROUND, mode_ok=True, acks={ARM: (m.MAV_RESULT_ACCEPTED, -3.0)})
    c.step(0.0, dataclasses.replace(GROUND, acks={ARM: (m.MAV_RESULT_ACCEPTED, -3.0)}))
    assert kinds(c.step(0.1, guided)) == [ActionKind.ARM]
    assert phase(c) is Phase.ARMING
    assert c.step(0.2, guided) == []  # the old ACK: still arming
    assert phase(c) is Phase.ARMING
    out = c.step(
        0.3, dataclasses.replace(guided, acks={ARM: (m.MAV_RESULT_ACCEPTED, 0.25)})
    )  # HEARTBEAT still says disarmed
    assert kinds(out) == [ActionKind.TAKEOFF] and phase(c) is Phase.TAKEOFF


def test_takeoff_timeout_grows_with_the_height() -> None:
    c = ctl(arm=True, takeoff_alt_m=10.0, mode_timeout_s=5.0)
    armed = dataclasses.replace(GROUND, mode_ok=True, armed=True)
    c.step(0.0, dataclasses.replace(GROUND, mode_ok=True))
    c.step(0.1, armed)
    assert phase(c) is Phase.TAKEOFF
    assert ActionKind.FAILED not in kinds(c.step(0.1 + 44.9, armed))
    out = c.step(0.1 + 45.1, armed)
    assert kinds(out) == [ActionKind.RESUME, ActionKind.FAILED]
    assert out[1].reason == "takeoff not confirmed within 45.0 s"


def test_already_armed_skips_arming() -> None:
    c = ctl(arm=True, takeoff_alt_m=5.0)
    assert kinds(c.step(0.0, dataclasses.replace(GROUND, armed=True))) == [ActionKind.STARTED, ActionKind.SET_MODE]
    assert phase(c) is Phase.MODE


def test_arming_failure_resumes_the_navigator_before_failing() -> None:
    c = ctl(arm=True, mode_timeout_s=1.0)
    guided = dataclasses.replace(GROUND, mode_ok=True)
    c.step(0.0, guided)
    assert phase(c) is Phase.ARMING
    out = c.step(1.5, guided)
    assert kinds(out) == [ActionKind.RESUME, ActionKind.FAILED] and out[1].reason.startswith("arming")


def px4(**kw: object) -> TakeoverController:
    return ctl(profile=Autopilot.PX4, **kw)


def test_px4_offboard_only_after_the_setpoint_prestream() -> None:
    c = px4(offboard_prestream_s=1.0)
    assert kinds(c.step(0.0, GROUND)) == [ActionKind.STARTED]  # the pre-stream only waits
    assert phase(c) is Phase.PRESTREAM
    t = 0.0
    while t < 1.0:
        c.note_prestream(t)
        assert c.step(t, GROUND) == []
        t = round(t + 0.1, 6)
    c.note_prestream(t)
    assert kinds(c.step(t, GROUND)) == [ActionKind.SET_MODE]
    assert phase(c) is Phase.MODE
    assert kinds(c.step(t + 0.1, dataclasses.replace(GROUND, mode_ok=True))) == [ActionKind.DONE]


def test_px4_a_gap_in_the_prestream_restarts_it() -> None:
    c = px4(offboard_prestream_s=1.0)
    c.step(0.0, GROUND)
    for t in (0.0, 0.4, 0.8):
        c.note_prestream(t)
    c.note_prestream(1.4)  # 0.6 s gap: starts again
    assert c.step(1.4, GROUND) == []
    c.note_prestream(2.4)
    assert c.step(2.4, GROUND) == []  # another 1 s gap: starts again at 2.4
    for t in (2.8, 3.2, 3.4):
        c.note_prestream(t)
    assert kinds(c.step(3.4, GROUND)) == [ActionKind.SET_MODE]


def test_px4_prestream_timeout() -> None:
    c = px4(mode_timeout_s=2.0)
    c.step(0.0, GROUND)
    out = c.step(7.01, GROUND)
    assert kinds(out) == [ActionKind.FAILED] and out[0].reason == "setpoint pre-stream not confirmed within 7.0 s"


def test_px4_takeoff_waits_for_the_global_position_and_commands_amsl() -> None:
    c = px4(arm=True, takeoff_alt_m=5.0)
    assert kinds(c.step(0.0, GROUND)) == [ActionKind.STARTED, ActionKind.SUSPEND, ActionKind.ARM]  # no mode first
    armed = dataclasses.replace(GROUND, armed=True)
    assert c.step(0.1, armed) == []
    assert phase(c) is Phase.GLOBAL_POSITION
    out = c.step(0.2, dataclasses.replace(armed, home_amsl_m=488.0))
    assert kinds(out) == [ActionKind.TAKEOFF] and out[0].value == pytest.approx(493.0)  # param7 is AMSL
    out = c.step(0.3, dataclasses.replace(armed, home_amsl_m=488.0, down_m=-4.5))
    assert kinds(out) == [ActionKind.AIRBORNE, ActionKind.RESUME]
    assert phase(c) is Phase.PRESTREAM


def test_px4_no_global_position_fails() -> None:
    c = px4(arm=True, takeoff_alt_m=5.0, mode_timeout_s=1.0)
    armed = dataclasses.replace(GROUND, armed=True)
    c.step(0.0, GROUND)
    c.step(0.1, armed)
    assert phase(c) is Phase.GLOBAL_POSITION
    out = c.step(1.2, armed)
    assert kinds(out) == [ActionKind.RESUME, ActionKind.FAILED] and out[1].reason.startswith("global position")


def test_a_new_goal_after_a_failure_starts_again() -> None:
    c = ctl(mode_timeout_s=1.0)
    c.step(0.0, GROUND)
    assert ActionKind.FAILED in kinds(c.step(1.5, GROUND))
    other = dataclasses.replace(GROUND, route=object())
    assert kinds(c.step(2.0, other)) == [ActionKind.STARTED, ActionKind.SET_MODE]


def test_takeoff_is_resent_only_without_an_accepted_ack_and_without_a_climb() -> None:
    c = ctl(arm=True, takeoff_alt_m=5.0)
    armed = dataclasses.replace(GROUND, mode_ok=True, armed=True)
    c.step(0.0, dataclasses.replace(GROUND, mode_ok=True))
    assert kinds(c.step(0.1, armed)) == [ActionKind.TAKEOFF]
    # no ACK, still on the ground: resent after COMMAND_RETRY_S (the first may have been lost)
    assert kinds(c.step(0.1 + COMMAND_RETRY_S, armed)) == [ActionKind.TAKEOFF]
    # ACCEPTED (ArduCopter spools up for seconds before it leaves the ground): not resent while it has not climbed
    acked = dataclasses.replace(armed, acks={TAKEOFF: (m.MAV_RESULT_ACCEPTED, 0.1 + COMMAND_RETRY_S + 0.05)})
    for k in range(2, 6):
        assert c.step(0.1 + k * COMMAND_RETRY_S, acked) == []
    # an ACCEPTED from before this phase does not count
    c2 = ctl(arm=True, takeoff_alt_m=5.0)
    c2.step(10.0, dataclasses.replace(GROUND, mode_ok=True))
    stale = dataclasses.replace(armed, acks={TAKEOFF: (m.MAV_RESULT_ACCEPTED, 1.0)})
    assert kinds(c2.step(10.1, stale)) == [ActionKind.TAKEOFF]
    assert kinds(c2.step(10.1 + COMMAND_RETRY_S, stale)) == [ActionKind.TAKEOFF]


def test_waits_for_a_position_estimate_before_taking_over_then_proceeds() -> None:
    c = ctl(arm=True, takeoff_alt_m=5.0, ready_timeout_s=30.0)
    no_pose = dataclasses.replace(GROUND, navigating=False, waiting=True, down_m=None, ekf_ready=False)
    assert kinds(c.step(0.0, no_pose)) == [ActionKind.STARTED]
    assert phase(c) is Phase.READY
    assert c.step(29.0, no_pose) == []  # nothing sent: GUIDED and arming would be refused before the EKF origin
    new_goal = dataclasses.replace(GROUND, down_m=None)  # NAVIGATING before its first cycle, still no pose
    assert c.step(29.2, new_goal) == []
    pose_no_ekf = dataclasses.replace(GROUND, ekf_ready=False)
    assert c.step(29.5, pose_no_ekf) == []
    assert kinds(c.step(29.9, GROUND)) == [ActionKind.SUSPEND, ActionKind.SET_MODE]
    assert phase(c) is Phase.MODE_BEFORE_ARM


def test_position_estimate_wait_is_bounded() -> None:
    c = ctl(arm=True, takeoff_alt_m=5.0, ready_timeout_s=30.0)
    no_pose = dataclasses.replace(GROUND, navigating=False, waiting=True, down_m=None, ekf_ready=False)
    c.step(0.0, no_pose)
    out = c.step(30.1, no_pose)
    assert kinds(out) == [ActionKind.FAILED]
    assert out[0].reason == "position estimate not confirmed within 30.0 s"
    assert phase(c) is Phase.IDLE


def test_on_a_lossy_link_a_mode_phase_waits_for_heartbeat_evidence_before_failing() -> None:
    """GUIDED is confirmed only by HEARTBEAT: past the deadline the phase fails once HEARTBEATS_TO_FAIL of them
    said "not yet"; with fewer (lost on the way) it waits on, resending, up to HARD_TIMEOUT_FACTOR x its timeout."""
    c = ctl(mode_timeout_s=2.0)
    heard = dataclasses.replace(GROUND, heartbeats=10)
    c.step(0.0, heard)
    out = c.step(2.5, dataclasses.replace(heard, heartbeats=11))  # one heartbeat in 2.5 s: the rest were lost
    assert kinds(out) == [ActionKind.SET_MODE] and phase(c) is Phase.MODE
    assert kinds(c.step(3.0, dataclasses.replace(heard, heartbeats=12, mode_ok=True))) == [ActionKind.DONE]


def test_a_refused_command_and_enough_heartbeats_saying_not_yet_fail_at_the_deadline() -> None:
    c = ctl(mode_timeout_s=2.0)
    c.step(0.0, dataclasses.replace(GROUND, heartbeats=0))
    refused = dataclasses.replace(GROUND, heartbeats=HEARTBEATS_TO_FAIL, acks={SET_MODE: (m.MAV_RESULT_FAILED, 0.1)})
    assert kinds(c.step(1.9, refused)) == [ActionKind.SET_MODE]
    out = c.step(2.01, refused)
    assert kinds(out) == [ActionKind.FAILED]


def test_unanswered_mode_commands_are_resent_past_the_deadline_up_to_the_hard_limit() -> None:
    """Seed 10 of the lossy-link batch: four DO_SET_MODE lost in a row. HEARTBEATs saying "not GUIDED" are no
    evidence of a refusal while no command has been answered; an ACK from before the phase is not an answer."""
    c = ctl(mode_timeout_s=2.0)
    c.step(0.0, dataclasses.replace(GROUND, heartbeats=0))
    unanswered = dataclasses.replace(GROUND, heartbeats=5, acks={SET_MODE: (m.MAV_RESULT_FAILED, -1.0)})
    for t in (2.01, 3.02):
        assert kinds(c.step(t, unanswered)) == [ActionKind.SET_MODE] and phase(c) is Phase.MODE
    assert c.step(3.99, unanswered) == [] and phase(c) is Phase.MODE
    out = c.step(HARD_TIMEOUT_FACTOR * 2.0 + 0.01, unanswered)
    assert kinds(out) == [ActionKind.FAILED] and out[0].reason == "GUIDED not confirmed within 2.0 s"


def test_an_accepted_mode_command_waits_for_heartbeats_after_its_answer() -> None:
    """ACCEPTED just before the deadline: the HEARTBEATs heard before it said "not yet" about a command that had
    not arrived; the phase fails only once HEARTBEATS_TO_FAIL more say so, and GUIDED in the next one ends it."""
    c = ctl(mode_timeout_s=2.0)
    c.step(0.0, dataclasses.replace(GROUND, heartbeats=0))
    accepted = dataclasses.replace(GROUND, heartbeats=4, acks={SET_MODE: (m.MAV_RESULT_ACCEPTED, 1.9)})
    c.step(1.95, accepted)
    assert ActionKind.FAILED not in kinds(c.step(2.5, dataclasses.replace(accepted, heartbeats=5)))
    assert kinds(c.step(2.9, dataclasses.replace(accepted, heartbeats=6, mode_ok=True))) == [ActionKind.DONE]
    c2 = ctl(mode_timeout_s=2.0)
    c2.step(0.0, dataclasses.replace(GROUND, heartbeats=0))
    c2.step(1.95, accepted)
    late = dataclasses.replace(accepted, heartbeats=4 + HEARTBEATS_TO_FAIL)
    assert kinds(c2.step(3.5, late)) == [ActionKind.FAILED]  # accepted, then three HEARTBEATs without GUIDED


def test_without_heartbeats_the_phase_still_fails_at_the_hard_limit() -> None:
    c = ctl(arm=True, mode_timeout_s=2.0)
    guided = dataclasses.replace(GROUND, mode_ok=True, heartbeats=5)
    c.step(0.0, guided)
    assert phase(c) is Phase.ARMING  # arming is confirmed by HEARTBEAT too
    assert ActionKind.FAILED not in kinds(c.step(HARD_TIMEOUT_FACTOR * 2.0 - 0.01, guided))
    out = c.step(HARD_TIMEOUT_FACTOR * 2.0 + 0.01, guided)
    assert kinds(out) == [ActionKind.RESUME, ActionKind.FAILED] and out[1].reason.startswith("arming")
