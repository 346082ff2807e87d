"""The service flies its default planner, bapf-nav, through a walled world over loopback (real MAVLink/UDP)."""

from __future__ import annotations

import math

import pytest

from apf_companion.config import ServiceConfig
from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.planning import BapfNavPlanner, PlannerParams
from sim.world.files import example_world_path, load_world

from . import test_service_flight
from .test_service_flight import GOAL, flight, service_config, wait_state

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


def test_the_default_planner_is_bapf_nav() -> None:
    assert ServiceConfig().planner.name == "bapf-nav"


async def test_bapf_nav_flies_out_of_the_u_trap(monkeypatch: pytest.MonkeyPatch) -> None:
    """The U opens towards the start and the straight line runs into its bottom: the paper's planners stop or
    graze there; bapf-nav backs out on its map of the walls and arrives, keeping radius + safety margin.

    A long flight (about 130 s simulated): a speed-up of 2 and a 10 s heartbeat timeout keep it honest on a
    loaded machine, where the simulator and the service share one event loop."""
    monkeypatch.setattr(test_service_flight, "SPEEDUP", 2.0)
    world = load_world(example_world_path("u-trap"))
    cfg = service_config(planner="bapf-nav", link={"connect": "udpin:127.0.0.1:0", "heartbeat_timeout_s": 10.0})
    async with flight(world, cfg, route=Route.point(*GOAL, source="test"), spawn_mode="LOITER") as (svc, sim):
        assert isinstance(svc.planner, BapfNavPlanner)
        try:
            state = await wait_state(svc, {State.ARRIVED, State.STUCK}, 260.0)
        except TimeoutError:
            pytest.fail(f"no end of flight: {svc.result()} {sim.result()} {svc.navigator.counters}")
        res = sim.result()
    assert state is State.ARRIVED, svc.result()
    assert not res["collided"]
    assert math.dist(res["final_pos_ned_m"][:2], GOAL[:2]) <= 0.7 + 0.3
    params = PlannerParams()
    # Walls are 0.2 m thick; the clearance is measured to their surface.
    assert res["min_clearance_m"] >= params.vehicle_radius_m + params.safety_margin_m
