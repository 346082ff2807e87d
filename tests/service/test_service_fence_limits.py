"""The autopilot's fence parameters read over real loopback MAVLink from the bundled simulator (PARAM_REQUEST_READ,
HOME_POSITION): ArduCopter's defaults move the yard's edges in by the margin, clip it to the circle round home and
refuse goals above the ceiling; a fence switched off in flight is taken out and put back; PX4's circle round home
refuses goals beyond it."""

from __future__ import annotations

import logging
import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from shapely.geometry import Polygon

from apf_companion.fence import FenceOutcome
from apf_companion.goal import Route
from sim.vehicle.testing import command_long
from tests.conftest import HANG_S, until
from tests.service.test_service_fence import YARD, with_station, yard_flight

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


async def test_arducopters_default_fence_parameters_shape_the_area_and_the_goals() -> None:
    """FENCE_TYPE 7, FENCE_MARGIN 2 m, FENCE_RADIUS 300 m, FENCE_ALT_MAX 100 m (the simulator switches the fence
    on when it serves one): the L moved in by 2 - C = 1.4 m, clipped to the circle round home (far outside it);
    a goal above 98 m is refused, one outside the circle too; the goal in the yard is taken."""
    assert YARD.area_ne_m is not None and YARD.goal_ne_m is not None
    async with yard_flight(YARD.area_ne_m, sim_params={}) as (svc, sim):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        result = fence.result
        assert result is not None and result.outcome is FenceOutcome.USED, result
        assert result.note.startswith("intersection of 2 inclusion zones, 1.4 m in from its edges")
        assert result.note.endswith("FENCE_MARGIN 2 m, circle of 300 m round home, ceiling 100 m")
        area = svc.planner.params.nav_area_ne_m
        assert isinstance(area, tuple) and len(area) == 6
        exact = Polygon(YARD.area_ne_m).buffer(-1.4)
        assert exact.buffer(0.02).covers(Polygon(area)) and Polygon(area).area >= 0.99 * exact.area
        assert fence.bounds.ceiling_m == 98.0 and fence.bounds.home_circle is not None
        north, east, radius = fence.bounds.home_circle
        assert math.hypot(north, east) < 0.05 and radius == pytest.approx(298.6)  # home: the local origin
        now = svc.clock.now()
        refused = svc.counters.bad_goals
        assert not svc.admission.admit(Route.point(*YARD.goal_ne_m, -99.0, source="test"), now)  # above the ceiling
        in_margin = Route.point(-3.0, 0.0, -5.0, source="test")
        assert not svc.admission.admit(in_margin, now)  # in the margin: outside the area
        assert svc.counters.bad_goals == refused + 2
        assert svc.admission.admit(Route.point(*YARD.goal_ne_m, -5.0, source="test"), now)
        status = svc.reporter.status_dict(svc.clock.now())["fence"]
        assert status["limits"] == "FENCE_MARGIN 2 m, circle of 300 m round home, ceiling 100 m"
        assert status["ceiling_m"] == 98.0
        assert sim.engine.params["FENCE_ENABLE"] == 1.0


async def test_fence_parameters_changed_in_flight_are_followed(caplog: pytest.LogCaptureFixture) -> None:
    """FENCE_ENABLE 0 (a ground station's PARAM_SET): the circle round home and the ceiling go, the uploaded L
    stays (a fence can be switched on at run time without the parameter). FENCE_TYPE 3 (no polygons) with the
    fence on: the L goes (said), the circle (now the area, on the moving grid) and the ceiling are back. Each
    within a read."""
    assert YARD.area_ne_m is not None
    caplog.set_level(logging.INFO, logger="apf_companion")
    async with yard_flight(YARD.area_ne_m, fence_poll_s=1.0, sim_params={}) as (svc, sim):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.bounds.ceiling_m is not None, HANG_S, "the fence in service")
        assert svc.planner.params.nav_area_ne_m is not None and fence.bounds.home_circle is not None
        sim.engine.params.set("FENCE_ENABLE", 0.0)
        await until(lambda: fence.bounds.ceiling_m is None, HANG_S, "the ceiling taken out")
        assert fence.bounds.home_circle is None and svc.planner.params.nav_area_ne_m is not None
        assert fence.result is not None and fence.result.note.endswith(
            "FENCE_ENABLE 0: no circle round home or ceiling"
        )
        sim.engine.params.set("FENCE_TYPE", 3.0)
        sim.engine.params.set("FENCE_ENABLE", 1.0)
        await until(lambda: len(svc.planner.params.nav_area_ne_m or ()) == 32, HANG_S, "the circle for the L")
        assert fence.bounds.ceiling_m == 98.0 and fence.bounds.home_circle is not None
        assert fence.changes == 2 and fence.failures == 0
    said = [getattr(r, "note", None) for r in caplog.records if r.getMessage() == "fence.area"]
    assert said[-1] == (
        "inclusion circle, 1.4 m in from its edges, 32 vertices; FENCE_MARGIN 2 m, circle of 300 m round home, "
        "ceiling 100 m, FENCE_TYPE without polygons: uploaded zones not used"
    )


async def test_a_fence_switched_on_by_command_brings_its_ceiling_within_a_read() -> None:
    """ArduPilot 4.6 with FENCE_ENABLE 0: a ground station sends MAV_CMD_DO_FENCE_ENABLE 1 (as an RC switch or
    FENCE_AUTOENABLE would switch it): the parameter stays 0, SYS_STATUS's GEOFENCE bit says it is on, and the
    service's next read takes the circle round home and the ceiling into service; switched off, they go."""
    assert YARD.area_ne_m is not None
    params = {"FENCE_ENABLE": 0.0}
    async with with_station(YARD.area_ne_m, fence_poll_s=1.0, sim_params=params) as (svc, sim, gcs):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.result is not None, HANG_S, "the fence read")
        assert fence.bounds.ceiling_m is None and svc.planner.params.nav_area_ne_m is not None
        ack = await command_long(gcs, mavlink.MAV_CMD_DO_FENCE_ENABLE, 1.0)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        await until(lambda: fence.bounds.ceiling_m == 98.0, HANG_S, "the ceiling in service")
        assert fence.switched_on and sim.engine.params["FENCE_ENABLE"] == 0.0
        assert fence.result is not None and "switched on (SYS_STATUS)" in fence.result.note
        ack = await command_long(gcs, mavlink.MAV_CMD_DO_FENCE_ENABLE, 0.0)
        await until(lambda: fence.bounds.ceiling_m is None, HANG_S, "the ceiling out of service")


async def test_px4s_circle_round_home_is_the_area_and_refuses_goals_beyond_it() -> None:
    """PX4 with GF_MAX_HOR_DIST 40 m and no uploaded fence: the circle is the area (80 m across: wider than the
    fixed grid's 76.8 m, so bapf-nav plans it on its moving grid; PX4 has no margin parameter), goals further
    than 40 m from home are refused, nearer ones flown. GF_ACTION set to 0 (None: PX4 checks no breach) takes the
    circle out within a read, and the goal at 41 m is flown."""
    params = {"GF_MAX_HOR_DIST": 40.0}
    async with yard_flight(None, profile="px4", sim_params=params, fence_poll_s=1.0) as (svc, sim):
        fence = svc.fence
        assert fence is not None
        await until(lambda: fence.bounds.home_circle is not None, HANG_S, "the circle round home")
        area = svc.planner.params.nav_area_ne_m
        assert isinstance(area, tuple) and len(area) == 32
        assert fence.result is not None and fence.result.note.startswith("inclusion circle of 32 vertices")
        now = svc.clock.now()
        assert not svc.admission.admit(Route.point(41.0, 0.0, -5.0, source="test"), now)
        assert svc.admission.admit(Route.point(39.0, 0.0, -5.0, source="test"), now)
        sim.engine.params.set("GF_ACTION", 0.0)
        await until(lambda: fence.bounds.home_circle is None, HANG_S, "the circle out of service")
        assert svc.planner.params.nav_area_ne_m is None
        assert fence.limits is not None and "GF_ACTION 0 (none): no circle round home" in str(fence.summary())
        assert svc.admission.admit(Route.point(41.0, 0.0, -5.0, source="test"), svc.clock.now())
