"""The autopilot's fence read over real loopback MAVLink from the bundled simulator, which serves a world file's
flying area as its fence (mission protocol, mission_type FENCE): bapf-nav then plans over it and flies the walled
world through it; without a fence, or with an area in the config, nothing changes."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.fence import FenceOutcome
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.planning import FlyingArea, KeepOuts
from apf_companion.service import CompanionService
from apf_companion.status import encode_status_json
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.vehicle.fence import fence_items
from sim.vehicle.testing import upload_fence
from sim.world import load_world
from tests.conftest import HANG_S, SimulatorClock, free_port, until
from tests.service.mavproxy import mavproxy_path, mavproxy_session
from tests.service.test_service_flight import SPEEDUP, _as_mapping, running, service_config, wait_state

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

YARD = load_world("yard-l")
#: ArduPilot's fence parameters that leave the uploaded zones as they are: no margin (bapf-nav keeps its own C),
#: no circle round home; the ceiling (FENCE_TYPE bit 1) stays.
EXACT = {"FENCE_MARGIN": 0.0, "FENCE_TYPE": 5.0}


def _config(profile: str = "ardupilot", **planner: Any) -> ServiceConfig:
    """test_service_flight's config with bapf-nav, its ``[planner]`` table updated with ``planner``."""
    base = _as_mapping(service_config(profile=profile, planner="bapf-nav"))
    base["planner"] |= planner
    return config_from_mapping(base)


@contextlib.asynccontextmanager
async def yard_flight(
    fence: FlyingArea | None,
    route: Route | None = None,
    keepouts: KeepOuts = (),
    links: tuple[str, ...] = (),
    profile: str = "ardupilot",
    sim_params: dict[str, float] | None = None,
    **planner: Any,
) -> AsyncIterator[tuple[CompanionService, Simulator]]:
    """The service (bapf-nav, its ``[planner]`` updated with ``planner``) and the simulator (``profile``) flying
    yard-l from its start, the simulator serving ``fence`` (and talking on ``links`` too: a ground station) with
    ``sim_params`` (default ``EXACT``: the served zones are the area to a centimetre)."""
    svc = await CompanionService.open(_config(profile, **planner), route=route, clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}", *links],
            world=YARD,
            profile=profile,
            speedup=SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=YARD.start_ne_m, airborne=True, alt_m=5.0),
            fence=fence,
            fence_keepouts=keepouts,
            params=(EXACT if profile == "ardupilot" else {}) if sim_params is None else sim_params,
        )
    )
    async with running(svc, sim):
        yield svc, sim


@contextlib.asynccontextmanager
async def with_station(
    fence: FlyingArea | None, profile: str = "ardupilot", **planner: Any
) -> AsyncIterator[tuple[CompanionService, Simulator, MavlinkLink]]:
    """``yard_flight`` with a ground station (system 255) on its own link to the simulator, which it has heard."""
    gcs = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=255, source_component=190)
    try:
        assert gcs.local_address is not None
        link = f"udpout:127.0.0.1:{gcs.local_address[1]}"
        async with yard_flight(fence, links=(link,), profile=profile, **planner) as (svc, sim):
            await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
            yield svc, sim, gcs
    finally:
        await gcs.aclose()


def _box(half_m: float) -> tuple[tuple[float, float], ...]:
    """A square of ``2 half_m`` round yard-l's start (north, east) [m]."""
    assert YARD.start_ne_m is not None
    n, e = YARD.start_ne_m
    return ((n - half_m, e - half_m), (n + half_m, e - half_m), (n + half_m, e + half_m), (n - half_m, e + half_m))


async def test_the_fence_becomes_the_flying_area_and_the_yard_is_flown_round_its_corner() -> None:
    """yard-l's L, served as the autopilot's fence: read within seconds of the first global position, to a
    centimetre; said once in a STATUSTEXT; the goal in the other arm is reached round the inner corner."""
    assert YARD.goal_ne_m is not None and YARD.area_ne_m is not None
    route = Route.point(*YARD.goal_ne_m, -5.0, source="test")
    async with yard_flight(YARD.area_ne_m, route=route) as (svc, sim):
        assert svc.fence is not None
        await until(lambda: svc.fence is not None and svc.fence.result is not None, HANG_S, "the fence read")
        result = svc.fence.result
        assert result is not None and result.outcome is FenceOutcome.USED, result
        area = svc.planner.params.nav_area_ne_m
        assert area is not None and len(area) == 6
        want: list[tuple[float, float]] = [(float(v[0]), float(v[1])) for v in YARD.area_ne_m]  # type: ignore[index]
        for got, (n0, e0) in zip(area, want, strict=True):
            assert isinstance(got, tuple) and abs(got[0] - n0) < 0.02 and abs(got[1] - e0) < 0.02
        assert svc.params.config.planner.params["nav_area_ne_m"] == [list(v) for v in area]  # PARAM_SET keeps it
        assert await wait_state(svc, {State.ARRIVED, State.STUCK}, 240.0) is State.ARRIVED, svc.result()
        res = sim.result()
        assert not res["collided"] and res["min_clearance_m"] >= 0.35
        assert svc.fence.download.unexpected == 0


#: A flower bed in yard-l's south-east arm, across the straight way from the inner corner to the goal: an exclusion
#: zone of the fence, with nothing in it to see.
BED = ((3.0, 11.5), (6.5, 11.5), (6.5, 14.5), (3.0, 14.5))


async def test_exclusion_zones_become_keep_out_zones_the_flight_goes_round() -> None:
    """yard-l's fence with an exclusion zone: the service plans over the L and keeps out of the bed, which nothing
    marks; the flight arrives and never enters it."""
    assert YARD.goal_ne_m is not None and YARD.area_ne_m is not None
    route = Route.point(*YARD.goal_ne_m, -5.0, source="test")
    async with yard_flight(YARD.area_ne_m, route=route, keepouts=(BED,)) as (svc, sim):
        await until(lambda: svc.fence is not None and svc.fence.result is not None, HANG_S, "the fence read")
        assert svc.fence is not None and svc.fence.result is not None
        want = "inclusion polygon of 6 vertices; 1 exclusion zone as keep-out zone; FENCE_MARGIN 0 m, ceiling 100 m"
        assert svc.fence.result.note == want
        (bed,) = svc.planner.params.nav_keepout_ne_m
        assert all(abs(n - n0) < 0.02 and abs(e - e0) < 0.02 for (n, e), (n0, e0) in zip(bed, BED, strict=True))
        assert await wait_state(svc, {State.ARRIVED, State.STUCK}, 240.0) is State.ARRIVED, svc.result()
        track = np.array(sim.engine.trajectory_ned_m)[:, :2]
    inside_by = np.minimum.reduce([track[:, 0] - 3.0, 6.5 - track[:, 0], track[:, 1] - 11.5, 14.5 - track[:, 1]])
    # Never in the bed: the plan keeps its edges at C = 0.6 m less a cell, the flown track 0.27-0.4 m (tracking).
    assert inside_by.max() <= -0.1
    assert (track[:, 1] > 15.0).any()  # and it got past the bed


async def test_a_fence_changed_in_flight_is_planned_over_and_a_removed_one_taken_out(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The ground station uploads a smaller fence while the vehicle hovers, then clears it: each is read again
    within ``fence_poll_s`` and put into service (a later PARAM_SET starts from it); the cleared one leaves no area."""
    caplog.set_level(logging.INFO, logger="apf_companion")
    polygons_only = EXACT | {"FENCE_TYPE": 4.0}  # no ceiling: a cleared fence is no fence at all
    async with yard_flight(YARD.area_ne_m, fence_poll_s=1.0, sim_params=polygons_only) as (svc, sim):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        assert len(_area(svc)) == 6
        box = _box(3.0)
        sim.engine.fence.set_zones(box)
        await until(lambda: len(_area(svc)) == 4, HANG_S, "the new fence in service")
        got = np.array(_area(svc))
        assert np.abs(got - np.array(box)).max() < 0.02
        assert svc.params.config.planner.params["nav_area_ne_m"] == [list(v) for v in _area(svc)]
        sim.engine.fence.set_zones(None)
        await until(lambda: svc.planner.params.nav_area_ne_m is None, HANG_S, "the cleared fence taken out")
        assert "nav_area_ne_m" not in svc.params.config.planner.params
        assert fence.changes == 2 and fence.failures == 0 and fence.reads >= 3
        assert fence.download.unexpected == 0
    said = [r for r in caplog.records if r.getMessage().startswith("fence.")]
    events = [(r.getMessage(), getattr(r, "changed", None), getattr(r, "removed", None)) for r in said]
    assert events == [("fence.area", False, None), ("fence.area", True, None), ("fence.none", None, True)]


async def test_a_flight_that_breaches_the_autopilots_fence_is_taken_over_by_its_return() -> None:
    """The simulated ArduPilot enforces its fence (FENCE_ACTION 1: RTL). The service reads the L once
    (``fence_poll_s`` 0) and the autopilot's fence is then shrunk to a box round the start: the flight to the goal
    leaves the box, the autopilot says so and returns home, and the service drops its goal without fighting it."""
    assert YARD.goal_ne_m is not None and YARD.area_ne_m is not None and YARD.start_ne_m is not None
    route = Route.point(*YARD.goal_ne_m, -5.0, source="test")
    async with yard_flight(YARD.area_ne_m, route=route, fence_poll_s=0.0) as (svc, sim):
        await until(lambda: svc.fence is not None and svc.fence.result is not None, HANG_S, "the fence read")
        sim.engine.fence.set_zones(_box(3.0))
        assert await wait_state(svc, {State.IDLE, State.ARRIVED, State.STUCK}, 120.0) is State.IDLE
        assert sim.engine.mode_name() == "RTL" and sim.engine.fence.guard.breaches == 1
        assert "Polygon fence breached" in [s.text for s in sim.engine.statustexts]


async def test_a_breach_the_autopilot_only_reports_is_in_the_status_record() -> None:
    """FENCE_ACTION 0 (report only): the autopilot keeps flying the service's setpoints outside its shrunk fence;
    SYS_STATUS's GEOFENCE health drops, and the service's status record says breached."""
    assert YARD.goal_ne_m is not None and YARD.area_ne_m is not None
    route = Route.point(*YARD.goal_ne_m, -5.0, source="test")
    params = EXACT | {"FENCE_ACTION": 0.0}
    async with yard_flight(YARD.area_ne_m, route=route, fence_poll_s=0.0, sim_params=params) as (svc, sim):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        sim.engine.fence.set_zones(_box(3.0))
        await until(lambda: fence.breached, HANG_S, "the breach reported")
        assert fence.breaches == 1 and sim.engine.mode_name() == "GUIDED" and svc.navigator.state is State.NAVIGATING
        status = json.loads(encode_status_json(svc.reporter.status_dict(svc.clock.now())))["fence"]
        assert status["breached"] is True and status["breaches"] == 1


async def test_a_ground_station_uploading_a_fence_is_waited_out_then_its_fence_is_flown() -> None:
    """A ground station uploads a new fence over its own link: while its upload is open the service's re-reads
    are DENIED (counted; the L stays in service), and once it is complete the new fence is in service."""
    async with with_station(YARD.area_ne_m, fence_poll_s=1.0) as (svc, sim, gcs):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        box = _box(3.0)
        items = fence_items(box, (), sim.engine.cfg.home)
        assert await upload_fence(gcs, items, stop_after=2) is None  # the upload left open
        await until(lambda: fence.failures >= 2, HANG_S, "re-reads refused while the upload is open")
        assert len(_area(svc)) == 6 and fence.changes == 0
        ack = await upload_fence(gcs, items)  # the same ground station starts again and completes it
        assert ack.type == mavlink.MAV_MISSION_ACCEPTED
        await until(lambda: len(_area(svc)) == 4, HANG_S, "the uploaded fence in service")
        assert np.abs(np.array(_area(svc)) - np.array(box)).max() < 0.02 and fence.changes == 1
        status = json.loads(encode_status_json(svc.reporter.status_dict(svc.clock.now())))["fence"]
        assert status["outcome"] == "used"
        assert status["note"] == "inclusion polygon of 4 vertices; FENCE_MARGIN 0 m, ceiling 100 m"
        assert status["changes"] == 1 and status["failures"] >= 2 and status["reads"] >= 2


@pytest.mark.skipif(mavproxy_path() is None, reason="MAVProxy not installed (pip install --no-deps MAVProxy)")
async def test_a_fence_loaded_in_mavproxy_is_planned_over(tmp_path: Path) -> None:
    """MAVProxy, a real ground station on its own link to the simulated autopilot, uploads a fence file
    (``fence load``, MAVProxy's mission-protocol fence module), then clears it (``fence clear``): the service
    reads each at its next poll."""
    mavproxy = mavproxy_path()
    assert mavproxy is not None and YARD.start_ne_m is not None
    port = free_port(socket.SOCK_DGRAM)
    async with yard_flight(YARD.area_ne_m, links=(f"udpout:127.0.0.1:{port}",), fence_poll_s=1.0) as (svc, sim):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        box = _box(4.0)
        lines = ["QGC WPL 110"] + [
            f"{i}\t0\t{mavlink.MAV_FRAME_GLOBAL}\t{cmd}\t{p1}\t0\t0\t0\t{lat * 1e-7:.7f}\t{lon * 1e-7:.7f}\t0\t1"
            for i, (cmd, p1, lat, lon) in enumerate(fence_items(box, (), sim.engine.cfg.home))
        ]
        (tmp_path / "box.txt").write_text("\n".join(lines) + "\n")
        async with mavproxy_session(mavproxy, f"udpin:127.0.0.1:{port}", "1", tmp_path) as gcs:
            await gcs.read_until("Detected vehicle 1:1")
            gcs.type_in(f"fence load {tmp_path / 'box.txt'}")
            await gcs.read_until("Loaded 4 ")
            await until(lambda: len(_area(svc)) == 4, HANG_S, "MAVProxy's fence in service")
            assert np.abs(np.array(_area(svc)) - np.array(box)).max() < 0.02
            gcs.type_in("fence clear")  # MISSION_CLEAR_ALL
            await until(lambda: svc.planner.params.nav_area_ne_m is None, HANG_S, "MAVProxy's clear in service")
        assert sim.engine.fence.uploads == 2 and fence.changes == 2


async def test_on_px4_the_services_reads_leave_a_ground_stations_upload_free() -> None:
    """PX4 keeps one transfer state for every link (mavlink_mission.cpp) and refuses an upload while a download is
    open. The service reads the (empty) fence every second and acks each read, count 0 included, so a ground
    station's upload goes through at once or at the next try; without the ack every try was refused."""
    async with with_station(None, profile="px4", fence_poll_s=1.0) as (svc, sim, gcs):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.reads >= 3, HANG_S, "three reads of the empty fence")
        acks: list[int] = []
        while len(acks) < 5 and (not acks or acks[-1] != mavlink.MAV_MISSION_ACCEPTED):
            acks.append((await upload_fence(gcs, fence_items(_box(3.0), (), sim.engine.cfg.home))).type)
        # A try that meets one of the service's reads (a few ms of each second) is refused, and is repeated.
        assert acks[-1] == mavlink.MAV_MISSION_ACCEPTED and len(acks) <= 2, acks
        await until(lambda: svc.planner.params.nav_area_ne_m is not None, HANG_S, "the uploaded fence in service")
        assert len(_area(svc)) == 4


async def test_on_px4_the_fence_id_spares_the_downloads_so_an_upload_meets_no_read() -> None:
    """PX4 gives its fence plan an id (MISSION_CURRENT fence_id at 1 Hz, MISSION_COUNT opaque_id): the service
    downloads the L once and then reads the parameters only, so a ground station's upload is accepted at its first
    try every time; the new fence's id brings one download, and the box is in service."""
    async with with_station(YARD.area_ne_m, profile="px4", fence_poll_s=1.0) as (svc, sim, gcs):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.skipped >= 3, HANG_S, "three reads spared their download")
        assert fence.reads - fence.skipped == 1 and len(_area(svc)) == 6
        for half in (3.0, 4.0, 3.0):  # three uploads, each a new id
            box = _box(half)
            ack = await upload_fence(gcs, fence_items(box, (), sim.engine.cfg.home))
            assert ack.type == mavlink.MAV_MISSION_ACCEPTED  # at the first try: no read was downloading
            await until(
                lambda box=box: len(_area(svc)) == 4 and abs(_area(svc)[0][0] - box[0][0]) < 0.02,  # type: ignore[misc]
                HANG_S,
                "the uploaded fence in service",
            )
        skipped = fence.skipped
        await until(lambda: fence.skipped >= skipped + 2, HANG_S, "the new fence's id spares the reads again")
        assert fence.reads - fence.skipped == 4 and fence.failures == 0
        status = json.loads(encode_status_json(svc.reporter.status_dict(svc.clock.now())))["fence"]
        assert status["skipped"] == fence.skipped


async def test_on_px4_a_new_fence_id_brings_the_new_fence_without_waiting_for_the_poll() -> None:
    """With a poll of an hour, a ground station's upload on PX4 is in service within seconds: MISSION_CURRENT's new
    fence id starts the read."""
    async with with_station(YARD.area_ne_m, profile="px4", fence_poll_s=3600.0) as (svc, sim, gcs):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        ack = await upload_fence(gcs, fence_items(_box(3.0), (), sim.engine.cfg.home))
        assert ack.type == mavlink.MAV_MISSION_ACCEPTED
        await until(lambda: len(_area(svc)) == 4, HANG_S, "the uploaded fence in service")
        assert (fence.early, fence.reads, fence.changes) == (1, 2, 1)  # the poll would be an hour later


def _area(svc: CompanionService) -> tuple[tuple[float, float], ...]:
    area = svc.planner.params.nav_area_ne_m
    assert isinstance(area, tuple)
    return area


async def test_no_fence_leaves_the_planner_as_configured() -> None:
    async with yard_flight(None) as (svc, _):
        assert svc.fence is not None
        await until(lambda: svc.fence is not None and svc.fence.result is not None, HANG_S, "the fence read")
        assert svc.fence.result is not None and svc.fence.result.outcome is FenceOutcome.NO_FENCE
        assert svc.planner.params.nav_area_ne_m is None
        assert svc.reporter.status_dict(svc.clock.now())["fence"]["outcome"] == "no fence"


@pytest.mark.parametrize(
    "planner",
    [{"params": {"nav_area_ne_m": [-3.0, -3.0, 23.0, 23.0]}}, {"fence_area": False}],
    ids=["area-in-config", "fence-off"],
)
async def test_an_area_in_the_config_or_fence_area_off_reads_no_fence(planner: dict[str, Any]) -> None:
    svc = await CompanionService.open(_config(**planner))
    try:
        assert svc.fence is None and svc.reporter.status_dict(0.0)["fence"] is None
    finally:
        await svc.aclose()
