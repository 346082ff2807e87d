"""The simulated autopilot enforces its fence (sim.vehicle.fencebreach): ArduPilot's AC_Fence checks and
ArduCopter's fence_check actions, PX4's GF_ACTION; stepped without sockets."""

from __future__ import annotations

from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POSITION, Autopilot
from sim.vehicle import EngineConfig, SpawnConfig, VehicleEngine
from sim.vehicle.fence import fence_items
from sim.vehicle.fencebreach import FenceKind, fence_names, fence_zones
from sim.vehicle.telemetry import sensor_flags

GCS = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
SQUARE = ((0.0, 0.0), (20.0, 0.0), (20.0, 20.0), (0.0, 20.0))
GEOFENCE = int(mavlink.MAV_SYS_STATUS_GEOFENCE)


def _engine(profile: Autopilot = Autopilot.ARDUPILOT, *, at: tuple[float, float] = (10.0, 10.0), **cfg: Any) -> Any:
    """A vehicle hovering at ``at`` (north, east) [m], 5 m up, in GUIDED (OFFBOARD on PX4)."""
    mode = "GUIDED" if profile is Autopilot.ARDUPILOT else "OFFBOARD"
    params = {"FENCE_ENABLE": 1.0} if profile is Autopilot.ARDUPILOT else {}
    params |= cfg.pop("params", {})
    spawn = SpawnConfig(pos_ne_m=at, airborne=True, alt_m=5.0, mode=mode)
    return VehicleEngine(
        EngineConfig(profile=profile, spawn=spawn, params=params, **cfg), n_links=1, emit=lambda link, msg: None
    )


def _fly_to(v: VehicleEngine, north: float, east: float, seconds: float, down: float = -5.0) -> None:
    """Stream a position setpoint at 10 Hz for ``seconds`` (stops when the vehicle leaves the guided mode)."""
    guided = v.custom_mode
    for _ in range(round(seconds * 10)):
        if v.custom_mode != guided:
            return
        msg = GCS.set_position_target_local_ned_encode(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, MASK_POSITION, north, east, down, 0, 0, 0, 0, 0, 0, 0, 0
        )
        v.handle(GCS.decode(bytearray(msg.pack(GCS))), 0)
        for _ in range(round(0.1 / v.dt)):
            v.step()


def _texts(v: VehicleEngine) -> list[str]:
    return [s.text for s in v.statustexts]


def test_leaving_the_polygon_is_a_breach_and_ardupilot_returns_home() -> None:
    """FENCE_ACTION 1 (the default): RTL; the GEOFENCE health bit is clear while breached, set again inside."""
    v = _engine(fence=SQUARE)
    _fly_to(v, 10.0, 30.0, 20.0)
    assert "Polygon fence breached" in _texts(v) and v.mode_name() == "RTL"
    assert v.fence.guard.breached == FenceKind.POLYGON and v.fence.guard.breaches == 1
    assert v.state.pos_ned_m[1] > 20.0 and not sensor_flags(v)[2] & GEOFENCE
    for _ in range(round(10.0 / v.dt)):  # RTL climbs and flies home, inside the square
        v.step()
    assert v.fence.guard.breached == FenceKind(0) and sensor_flags(v)[2] & GEOFENCE


@pytest.mark.parametrize(
    ("action", "mode"), [(0, "GUIDED"), (2, "LAND"), (3, "RTL"), (4, "BRAKE"), (5, "LAND"), (6, "RTL")]
)
def test_fence_action_says_what_ardupilot_does(action: int, mode: str) -> None:
    v = _engine(fence=SQUARE, params={"FENCE_ACTION": float(action)})
    _fly_to(v, 10.0, 30.0, 8.0 if action == 0 else 20.0)
    assert "Polygon fence breached" in _texts(v) and v.mode_name() == mode
    assert v.fence.guard.breaches == 1  # report only: one breach, however long it lasts


def test_the_circle_round_home_and_the_ceiling_are_breaches_and_an_exclusion_zone_too() -> None:
    v = _engine(params={"FENCE_RADIUS": 15.0}, at=(0.0, 0.0))  # FENCE_TYPE 7: ceiling, circle; no polygons
    _fly_to(v, 0.0, 25.0, 20.0)
    assert "Circle fence breached" in _texts(v) and v.mode_name() == "RTL"
    v = _engine(params={"FENCE_ALT_MAX": 8.0}, at=(0.0, 0.0))
    _fly_to(v, 0.0, 0.0, 20.0, down=-12.0)
    assert "Max Alt fence breached" in _texts(v) and v.mode_name() == "RTL"
    bed = ((8.0, 12.0), (12.0, 12.0), (12.0, 16.0), (8.0, 16.0))
    v = _engine(fence=SQUARE, fence_keepouts=(bed,), at=(10.0, 5.0))
    _fly_to(v, 10.0, 18.0, 20.0)
    assert "Polygon fence breached" in _texts(v) and v.state.pos_ned_m[1] > 12.0


def test_a_fence_switched_off_or_report_only_lets_the_flight_go_on() -> None:
    v = _engine(fence=SQUARE, params={"FENCE_ENABLE": 0.0})
    _fly_to(v, 10.0, 30.0, 20.0)
    assert v.mode_name() == "GUIDED" and v.state.pos_ned_m[1] > 29.0 and v.fence.guard.breaches == 0
    assert not any("breached" in t for t in _texts(v))


def test_a_breach_more_than_100_m_out_lands() -> None:
    v = _engine(fence=SQUARE, at=(140.0, 10.0))  # spawned 120 m outside
    v.step()
    assert v.mode_name() == "LAND" and "Polygon fence breached" in _texts(v)


def _arm(v: VehicleEngine, out: list[Any], *, force: bool = False) -> int:
    """MAV_CMD_COMPONENT_ARM_DISARM (21196 in param2 forces it); the COMMAND_ACK's result."""
    out.clear()
    magic = 21196 if force else 0
    msg = GCS.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, magic, 0, 0, 0, 0, 0)
    v.handle(GCS.decode(bytearray(msg.pack(GCS))), 0)
    return int(next(m.result for m in out if m.get_type() == "COMMAND_ACK"))


@pytest.mark.parametrize("enable", [1.0, 0.0])
def test_on_the_ground_a_breach_is_recorded_refuses_arming_and_is_not_acted_on(enable: float) -> None:
    """AC_Fence::pre_arm_check through AP_Arming::fence_checks: "Vehicle breaching Polygon fence" while the fence
    is on; a forced arm skips it. Off, nothing is breached."""
    out: list[Any] = []
    cfg = EngineConfig(fence=SQUARE, spawn=SpawnConfig(pos_ne_m=(30.0, 30.0)), params={"FENCE_ENABLE": enable})
    v = VehicleEngine(cfg, n_links=1, emit=lambda link, msg: out.append(msg))
    v.step()
    assert v.fence.guard.breaches == 0 and not any("breached" in t for t in _texts(v))
    if enable == 0.0:
        assert v.fence.guard.breached == FenceKind(0) and _arm(v, out) == mavlink.MAV_RESULT_ACCEPTED
        return
    assert v.fence.guard.breached == FenceKind.POLYGON
    assert _arm(v, out) == mavlink.MAV_RESULT_FAILED and not v.armed
    assert "PreArm: Vehicle breaching Polygon fence" in _texts(v)
    assert _arm(v, out, force=True) == mavlink.MAV_RESULT_ACCEPTED and v.armed


@pytest.mark.parametrize(("action", "mode"), [(1, "OFFBOARD"), (2, "AUTO.LOITER"), (3, "AUTO.RTL"), (5, "AUTO.LAND")])
def test_px4_acts_on_gf_action(action: int, mode: str) -> None:
    v = _engine(Autopilot.PX4, fence=SQUARE, params={"GF_ACTION": float(action)})
    _fly_to(v, 10.0, 30.0, 8.0 if action == 1 else 20.0)
    assert "Geofence violation" in _texts(v) and v.mode_name() == mode


def test_px4_with_gf_action_none_checks_nothing_and_its_inclusion_zones_are_a_union() -> None:
    v = _engine(Autopilot.PX4, fence=SQUARE, params={"GF_ACTION": 0.0, "GF_MAX_HOR_DIST": 5.0})
    _fly_to(v, 10.0, 30.0, 20.0)
    assert v.fence.guard.breaches == 0 and v.mode_name() == "OFFBOARD"
    v = _engine(Autopilot.PX4, params={"GF_MAX_VER_DIST": 8.0}, at=(0.0, 0.0))
    _fly_to(v, 0.0, 0.0, 20.0, down=-12.0)
    assert "Geofence violation" in _texts(v) and v.mode_name() == "AUTO.LOITER"
    v = _engine(Autopilot.PX4, fence=SQUARE)  # a second inclusion zone east of the square: one of them will do
    east = ((0.0, 19.0), (20.0, 19.0), (20.0, 40.0), (0.0, 40.0))
    v.fence.items = v.fence.items + fence_items(east, (), v.fence.home)
    _fly_to(v, 10.0, 30.0, 20.0)
    assert v.fence.guard.breaches == 0 and v.state.pos_ned_m[1] > 29.0


def test_px4_refuses_to_arm_outside_its_geofence_while_it_checks_one() -> None:
    """PX4's commander: "Arming denied, vehicle outside geofence" while GF_ACTION is not None."""
    for action, refused in ((2.0, True), (0.0, False)):
        out: list[Any] = []
        spawn = SpawnConfig(pos_ne_m=(30.0, 30.0))
        cfg = EngineConfig(profile=Autopilot.PX4, fence=SQUARE, spawn=spawn, params={"GF_ACTION": action})
        v = VehicleEngine(cfg, n_links=1, emit=lambda link, msg, out=out: out.append(msg))  # type: ignore[misc]
        v.step()
        result = _arm(v, out)
        assert (result == mavlink.MAV_RESULT_ACCEPTED) is not refused and v.armed is not refused
        assert ("Arming denied, vehicle outside geofence" in _texts(v)) is refused


def test_fence_names_are_ardupilots() -> None:
    assert fence_names(FenceKind.POLYGON) == "Polygon fence"
    assert fence_names(FenceKind.ALT_MAX | FenceKind.CIRCLE) == "Max Alt and Circle fences"


def test_fence_zones_read_the_items_as_the_autopilot_holds_them() -> None:
    v = _engine(fence=SQUARE, fence_keepouts=(((8.0, 8.0), (12.0, 8.0), (12.0, 12.0)),))
    circle = (int(mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION), 2.0, *v.fence.items[0][2:])  # round the first vertex
    zones = fence_zones([*v.fence.items, circle], v.fence.home)
    assert len(zones.inclusion) == 1 and len(zones.exclusion) == 2
    assert zones.inclusion[0].area == pytest.approx(400.0, rel=1e-3)  # vertices to 1e-7 deg: about 1 cm
    assert zones.exclusion[1].area == pytest.approx(3.1416 * 4.0, rel=0.02)
