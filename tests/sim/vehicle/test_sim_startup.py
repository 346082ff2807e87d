"""The ArduPilot profile starts like a real ArduCopter (issue 8), over loopback UDP with a pymavlink client.

- no position before the EKF origin (SITL: about 20 s): no LOCAL_POSITION_NED / HOME_POSITION, GLOBAL_POSITION_INT
  with the stale zero location, GUIDED refused ("requires position"), arming in GUIDED refused ("PreArm: Need
  Position Estimate"), NAV_TAKEOFF refused; EKF_STATUS_REPORT without horizontal position (sim/vehicle/startup.py);
- HEARTBEAT only until streams are requested (SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM); an unknown message id is
  DENIED (``GCS_Common.cpp`` set_message_interval).

The vehicle runs 20x faster than real time; every wait is on the simulated clock.
"""

from __future__ import annotations

from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.links import MavlinkLink
from sim.vehicle import RangeSensorConfig, SpawnConfig
from sim.vehicle.startup import EKF_FLAGS_NO_ORIGIN, EKF_FLAGS_ORIGIN, ORIGIN_TEXT
from sim.vehicle.testing import command_long, drain, simulator_with_client
from tests.conftest import wait_sim_time

SPEEDUP = 20.0
ORIGIN_S = 20.0  # SIM_EKF_ORIGIN_S default
NOT_A_MESSAGE = 12345  # no MAVLink message has this id: ArduPilot has no ap_message for it


def types(msgs: list[Any]) -> set[str]:
    return {msg.get_type() for msg in msgs}


def interval(msg_id: int, hz: float) -> tuple[int, float, float]:
    return (m.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), 1e6 / hz)


async def test_fresh_ardupilot_sends_only_heartbeat_until_asked() -> None:
    # the bundled range sensor (OBSTACLE_DISTANCE) stands for a separate device, not the autopilot: off here
    cfg: dict[str, Any] = {"unasked_streams": None, "sensor": RangeSensorConfig(messages=frozenset())}
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, **cfg) as (sim, gcs):
        await wait_sim_time(sim, 3.0)
        seen = await drain(gcs)
        assert types(seen) <= {"HEARTBEAT", "STATUSTEXT"} and "HEARTBEAT" in types(seen)
        # SET_MESSAGE_INTERVAL: that message, on this link
        ack = await command_long(gcs, *interval(m.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10.0))
        assert ack.result == m.MAV_RESULT_ACCEPTED
        await gcs.recv_match(type="LOCAL_POSITION_NED", timeout=5.0)
        # REQUEST_DATA_STREAM: the stream's messages (EXTRA1 = ATTITUDE in ArduCopter's GCS_MAVLink_Copter.cpp)
        gcs.send(gcs.mav.request_data_stream_encode(1, 1, m.MAV_DATA_STREAM_EXTRA1, 4, 1))
        await gcs.recv_match(type="ATTITUDE", timeout=5.0)
        t0 = sim.t_s
        await wait_sim_time(sim, t0 + 2.0)
        assert types(await drain(gcs)) <= {"HEARTBEAT", "STATUSTEXT", "LOCAL_POSITION_NED", "ATTITUDE"}
        # and stopping it again
        gcs.send(gcs.mav.request_data_stream_encode(1, 1, m.MAV_DATA_STREAM_EXTRA1, 0, 0))
        await wait_sim_time(sim, sim.t_s + 1.0)
        await drain(gcs)
        await wait_sim_time(sim, sim.t_s + 2.0)
        assert "ATTITUDE" not in types(await drain(gcs))


async def test_unknown_message_interval_is_denied() -> None:
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, unasked_streams=None) as (_sim, gcs):
        ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, NOT_A_MESSAGE, 100_000.0)
        assert ack.result == m.MAV_RESULT_DENIED
        ack = await command_long(gcs, *interval(m.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 2.0))
        assert ack.result == m.MAV_RESULT_ACCEPTED


async def _request(gcs: MavlinkLink, *ids: int) -> None:
    for msg_id in ids:
        ack = await command_long(gcs, *interval(msg_id, 5.0))
        assert ack.result == m.MAV_RESULT_ACCEPTED


async def test_no_position_until_the_ekf_origin() -> None:
    spawn = SpawnConfig(pos_ne_m=(2.0, 1.0), mode="GUIDED")
    cfg: dict[str, Any] = {"fast_start": False, "unasked_streams": None, "spawn": spawn}
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, **cfg) as (sim, gcs):
        await _request(
            gcs,
            m.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
            m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
            m.MAVLINK_MSG_ID_HOME_POSITION,
            m.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
        )
        texts: list[str] = []
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, texts=texts)
        assert ack.result == m.MAV_RESULT_FAILED and "PreArm: Need Position Estimate" in texts
        ack = await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0)
        assert ack.result == m.MAV_RESULT_FAILED
        # no home yet: FAILED (GCS_Common.cpp handle_command_get_home_position); MAVProxy asks this at connect
        ack = await command_long(gcs, m.MAV_CMD_GET_HOME_POSITION)
        assert ack.result == m.MAV_RESULT_FAILED
        await command_long(gcs, m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0)  # STABILIZE
        texts.clear()
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, texts=texts)
        assert ack.result == m.MAV_RESULT_FAILED and "Mode change to GUIDED failed: requires position" in texts
        await wait_sim_time(sim, ORIGIN_S - 2.0)
        before = await drain(gcs)
        assert "LOCAL_POSITION_NED" not in types(before) and "HOME_POSITION" not in types(before)
        glob = [msg for msg in before if msg.get_type() == "GLOBAL_POSITION_INT"]
        assert glob and all(msg.lat == 0 and msg.lon == 0 for msg in glob)  # sent, with the stale zero location
        ekf = [msg.flags for msg in before if msg.get_type() == "EKF_STATUS_REPORT"]
        assert ekf and set(ekf) == {EKF_FLAGS_NO_ORIGIN}
        assert not sim.vehicle.armed and sim.vehicle.mode == "STABILIZE"
        # the origin: position, home, GUIDED and arming become available
        await wait_sim_time(sim, ORIGIN_S + 1.0)
        after = await drain(gcs)
        assert {"LOCAL_POSITION_NED", "HOME_POSITION"} <= types(after)
        assert any(msg.get_type() == "STATUSTEXT" and msg.text == ORIGIN_TEXT for msg in after)
        assert [msg.flags for msg in after if msg.get_type() == "EKF_STATUS_REPORT"][-1] == EKF_FLAGS_ORIGIN
        assert sim.engine.startup.origin_t_s == pytest.approx(ORIGIN_S, abs=0.02)
        ack = await command_long(gcs, m.MAV_CMD_GET_HOME_POSITION)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == m.MAV_RESULT_ACCEPTED


async def test_fast_start_and_the_parameter() -> None:
    """``fast_start`` (tests, ``apf-sim fly``) sets the origin at boot; SIM_EKF_ORIGIN_S is a parameter."""
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, unasked_streams=None) as (sim, gcs):
        assert sim.engine.startup.origin_set
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
        assert ack.result == m.MAV_RESULT_ACCEPTED
    cfg: dict[str, Any] = {"fast_start": False, "params": {"SIM_EKF_ORIGIN_S": 2.0}}
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, **cfg) as (sim, gcs):
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"SIM_EKF_ORIGIN_S", -1))
        value = await gcs.recv_match(type="PARAM_VALUE", timeout=5.0)
        assert value.param_value == pytest.approx(2.0)
        await wait_sim_time(sim, 2.5)
        assert sim.engine.startup.origin_t_s == pytest.approx(2.0, abs=0.02)


async def test_stream_rate_parameters_at_boot() -> None:
    """SRn_<group> (GCS_MAVLink_Copter.cpp stream rates, read at boot): SR0_POSITION streams the position group on
    link 0 unasked; the other groups stay off."""
    cfg: dict[str, Any] = {
        "unasked_streams": None,
        "params": {"SR0_POSITION": 5.0},
        "sensor": RangeSensorConfig(messages=frozenset()),
    }
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, **cfg) as (sim, gcs):
        await wait_sim_time(sim, 2.0)
        seen = types(await drain(gcs))
        assert {"LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"} <= seen
        assert seen <= {"HEARTBEAT", "STATUSTEXT", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"}


async def test_the_ekf_origin_is_lost_at_a_reboot_and_set_again_after_the_delay() -> None:
    """A reboot restarts the EKF: no origin until SIM_EKF_ORIGIN_S after the new boot (sim/vehicle/reboot.py)."""
    cfg: dict[str, Any] = {"fast_start": False, "params": {"SIM_EKF_ORIGIN_S": 2.0}}
    async with simulator_with_client(profile="ardupilot", speedup=SPEEDUP, **cfg) as (sim, gcs):
        await wait_sim_time(sim, 2.5)
        assert sim.engine.startup.origin_set
        ack = await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1.0)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        boot_t = sim.engine.boot.boot_t_s
        assert not sim.engine.startup.origin_set
        await wait_sim_time(sim, boot_t + 2.5)
        assert sim.engine.startup.origin_set
        assert sim.engine.startup.origin_t_s == pytest.approx(boot_t + 2.0, abs=0.02)
