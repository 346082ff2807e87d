"""Restart without resume: a service process that starts while the vehicle already flies in GUIDED (the previous
process was stopped mid-flight) holds position and says why; the goal in its config file is not fresh unless
``goal.fly_after_restart``; a goal sent now is flown. Real loopback UDP against the bundled simulator, which keeps
flying between the two service processes (the second binds the same port the simulator sends to)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import AsyncIterator
from typing import Any

import pytest

from apf_companion.autopilot import MASK_VELOCITY, CopterMode
from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from apf_companion.setpoint import SetpointKind
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.world import World
from tests.conftest import SimulatorClock, free_port, until, wait_sim_time
from tests.service.test_service_flight import SPEEDUP, service_config

pytestmark = [pytest.mark.timeout(180)]

GOAL_NE_M = (25.0, 3.0)


def _config(port: int, **goal: Any) -> Any:
    return service_config(
        link={"connect": f"udpin:127.0.0.1:{port}"},
        goal={"north_m": GOAL_NE_M[0], "east_m": GOAL_NE_M[1], "down_m": -5.0} | goal,
    )


@contextlib.asynccontextmanager
async def service(cfg: Any, sim: Simulator, route: Route | None = None) -> AsyncIterator[CompanionService]:
    clock = SimulatorClock(SPEEDUP)
    svc = await CompanionService.open(cfg, clock=clock, route=route)
    clock.follow(sim)
    task = asyncio.create_task(svc.run())
    try:
        yield svc
    finally:
        svc.stop()
        await task


@contextlib.asynccontextmanager
async def airborne_in_guided(port: int) -> AsyncIterator[Simulator]:
    """The first service flies towards the config goal; the body starts once it is gone, mid-flight."""
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{port}"],
            profile="ardupilot",
            world=World.empty(),
            speedup=SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=True, alt_m=5.0, mode="LOITER"),
        )
    )
    try:
        async with service(_config(port), sim) as first:
            await until(lambda: first.navigator.counters.planner_steps > 10, what="the first service flies")
            assert first.navigator.engaged
        assert sim.vehicle.mode == "GUIDED" and sim.vehicle.armed
        assert math.hypot(*sim.vehicle.vel_ned_m_s[:2]) > 0.05  # still moving when the process is gone
        yield sim
    finally:
        await sim.aclose()


async def test_a_restarted_service_holds_instead_of_resuming_the_config_goal() -> None:
    port = free_port(socket.SOCK_DGRAM)
    async with airborne_in_guided(port) as sim, service(_config(port), sim) as svc:
        await until(lambda: svc.navigator.state is State.HOLDING, what="holding after the restart")
        await until(lambda: "fresh goal" in svc.reporter.reason, what="the reason reported (STATUSTEXT)")
        assert "fly_after_restart" in svc.reporter.reason
        await until(lambda: svc.outbox.last_setpoint is not None, what="a hold setpoint")
        t0 = sim.t_s
        held_at = list(sim.vehicle.pos_ned_m[:2])
        await wait_sim_time(sim, t0 + 6.0)  # two GUID_TIMEOUTs: long enough for any resumed motion to show
        assert svc.navigator.route is None and svc.navigator.counters.planner_steps == 0
        last = svc.outbox.last_setpoint
        assert last is not None and last.kind in (SetpointKind.HOLD, SetpointKind.BRAKE)
        assert last.type_mask == MASK_VELOCITY or last.vel_ned_m_s == (0.0, 0.0, 0.0)
        assert math.dist(sim.vehicle.pos_ned_m[:2].tolist(), held_at) < 1.0  # the vehicle stays where it was
        assert math.hypot(*sim.vehicle.vel_ned_m_s[:2]) < 0.1
        # A goal sent now is fresh: flown.
        assert svc.admission.admit(Route.point(*GOAL_NE_M, -5.0, source="gcs"), svc.clock.now())
        await until(lambda: svc.navigator.counters.planner_steps > 5, what="flying the fresh goal")
        assert svc.navigator.state is State.NAVIGATING


async def test_with_fly_after_restart_the_config_goal_is_flown() -> None:
    port = free_port(socket.SOCK_DGRAM)
    async with airborne_in_guided(port) as sim, service(_config(port, fly_after_restart=True), sim) as svc:
        await until(lambda: svc.navigator.counters.planner_steps > 5, what="flying the config goal again")
        assert svc.navigator.route is not None and svc.navigator.route.source == "config"


async def test_the_pilot_taking_the_vehicle_ends_the_restart_hold() -> None:
    port = free_port(socket.SOCK_DGRAM)
    async with airborne_in_guided(port) as sim, service(_config(port), sim) as svc:
        await until(lambda: svc.navigator.state is State.HOLDING, what="holding after the restart")
        sim.engine.set_mode(int(CopterMode.LOITER), "the pilot")
        await until(lambda: svc.navigator.state is State.IDLE, what="idle: never fight the pilot")
        n = svc.outbox.setpoints_sent
        await wait_sim_time(sim, sim.t_s + 2.0)
        assert svc.outbox.setpoints_sent == n
