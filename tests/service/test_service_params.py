"""Planner and safety parameters over MAVLink: a pymavlink ground station lists, reads and sets them over loopback
UDP while the service flies the scripted autopilot; refused values are echoed back unchanged with a STATUSTEXT."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.builders import planner_params
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.errors import ConfigError
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.links.messages import ParamSet, Source
from apf_companion.navigator import NavigatorParams, State
from apf_companion.observe import PlanTap
from apf_companion.outbox import Outbox
from apf_companion.params import PARAMS, REFUSED_INTERVAL_S, SET_LOG_INTERVAL_S, ParamServer, config_with
from apf_companion.planning.params import PlannerParams
from apf_companion.reporter import ServiceCounters
from apf_companion.service import CompanionService, build_planner
from apf_companion.setpoint import SetpointKind
from tests.conftest import HANG_S, counter_advances, until, within
from tests.service.mavproxy import mavproxy_path, mavproxy_session
from tests.service.test_service_mavlink import TICK_S, fast_config, gcs_for, rig

pytestmark = pytest.mark.timeout(60)


async def param_values(gcs: MavlinkLink, n: int, timeout_s: float = 5.0) -> list[Any]:
    out: list[Any] = []
    while len(out) < n:
        msg = await gcs.recv_match(type="PARAM_VALUE", timeout=timeout_s)
        out.append(msg)
    return out


async def set_param(
    gcs: MavlinkLink, name: str, value: float, seen: list[Any] | None = None, target: tuple[int, int] = (1, 191)
) -> Any:
    """PARAM_SET, then the PARAM_VALUE answering it; every other message read meanwhile goes to ``seen``."""
    gcs.send(gcs.mav.param_set_encode(*target, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32))
    while True:
        msg = await gcs.recv(timeout=5.0)
        if msg.get_type() == "PARAM_VALUE" and msg.param_id == name:
            return msg
        if seen is not None:
            seen.append(msg)


async def next_cycle(svc: CompanionService) -> None:
    """Until a planning cycle has started since now: the PARAM_SETs accepted before it are in service."""
    await counter_advances(lambda: svc.navigator.counters.cycles, 1, "a cycle")


def test_the_table_names_fit_and_map_to_real_keys() -> None:
    cfg = fast_config()
    names = [p.name for p in PARAMS]
    assert len(set(names)) == len(names) and all(len(n) <= 16 for n in names)
    planner = CompanionService(cfg).planner
    for spec in PARAMS:  # every key resolves, and setting it to its own value validates
        value = float(getattr(planner.params, spec.key.split(".")[-1], math.nan))
        if math.isnan(value):
            section, field = spec.key.split(".")
            value = float(getattr(getattr(cfg, section), field))
        config_with(cfg, planner.params, spec, value)


def test_the_docs_table_lists_every_parameter() -> None:
    page = (Path(__file__).resolve().parents[2] / "docs" / "ecosystem.md").read_text()
    for spec in PARAMS:
        assert f"| `{spec.name}` | `{spec.key}` |" in page, spec.name


async def test_list_read_by_name_and_index() -> None:
    async with rig(route=Route.point(20.0, 0.0, -5.0, source="test")) as (svc, _ap), gcs_for(svc) as gcs:
        gcs.send(gcs.mav.param_request_list_encode(1, 191))
        listed = await param_values(gcs, len(PARAMS))
        assert [m.param_index for m in listed] == list(range(len(PARAMS)))
        assert {m.param_count for m in listed} == {len(PARAMS)}
        assert all(m.get_srcComponent() == 191 for m in listed)
        by_name = {m.param_id: m for m in listed}
        assert by_name["APF_RHO_L"].param_value == pytest.approx(PlannerParams().rho_l_m)
        assert by_name["APF_N_BACT"].param_type == mavlink.MAV_PARAM_TYPE_INT32
        assert by_name["APF_RESUME_LINK"].param_value == 1.0
        # read by name (param_index -1) and by index; an unknown name gets no answer
        gcs.send(gcs.mav.param_request_read_encode(1, 191, b"APF_NOGOOD", -1))
        gcs.send(gcs.mav.param_request_read_encode(1, 191, b"APF_CRUISE_SPD", -1))
        msg = (await param_values(gcs, 1))[0]
        assert msg.param_id == "APF_CRUISE_SPD" and msg.param_value == pytest.approx(1.0)
        gcs.send(gcs.mav.param_request_read_encode(1, 191, b"", 2))
        msg = (await param_values(gcs, 1))[0]
        assert (msg.param_id, msg.param_index) == (PARAMS[2].name, 2)
        # a broadcast list (target_system 0, target_component 0) is answered too; another component's is not
        gcs.send(gcs.mav.param_request_list_encode(1, 1))
        gcs.send(gcs.mav.param_request_list_encode(0, 0))
        again = await param_values(gcs, len(PARAMS))
        assert [m.param_index for m in again] == list(range(len(PARAMS)))
        assert svc.counters.param_requests == 5


async def test_set_valid_value_is_used_by_the_running_planner() -> None:
    cfg = fast_config(cycle={"cruise_speed_m_s": 2.0})
    async with rig(cfg, route=Route.point(40.0, 0.0, -5.0, source="test")) as (svc, ap), gcs_for(svc) as gcs:
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        msg = await set_param(gcs, "APF_RHO_L", 0.6)
        assert msg.param_value == pytest.approx(0.6) and msg.param_index == 65535  # -1 in a uint16
        assert svc.params.planner_params.rho_l_m == 0.6  # the float32 meant, not 0.6000000238418579
        await next_cycle(svc)  # in service from the next cycle on
        assert svc.config.planner.params["rho_l_m"] == 0.6 and svc.planner.params.rho_l_m == 0.6
        msg = await set_param(gcs, "APF_CRUISE_SPD", 0.3)
        assert msg.param_value == pytest.approx(0.3)
        await next_cycle(svc)
        assert svc.navigator.params.cruise_speed_m_s == pytest.approx(0.3)
        tap = svc.navigator.planner  # behind the observers' tap, as at start: the recording sees the new planner
        assert isinstance(tap, PlanTap) and tap.planner is svc.planner
        n_before = len(ap.setpoints())

        def speeds() -> list[float]:
            new = ap.setpoints()[n_before:]
            return [math.hypot(m.vx, m.vy) for _, m in new if math.hypot(m.vx, m.vy) > 0]

        await within(svc.clock.now, lambda: len(speeds()) > 10, 10.0, "setpoints after the change")
        assert max(speeds()) <= 0.3 + 1e-6  # the feed-forward follows the new cruise speed
        msg = await set_param(gcs, "APF_SILENT_DRIFT", 0.5)  # 16 characters: param_id without a NUL
        await next_cycle(svc)
        assert msg.param_value == pytest.approx(0.5) and svc.navigator.params.silent_drift_m == 0.5
        assert svc.params.sets == 3 and svc.params.refused == 0
        assert svc.navigator.state is State.NAVIGATING
        assert svc.navigator.last_output is not None
        sp = svc.navigator.last_output.setpoint
        assert sp is not None and sp.kind is SetpointKind.NAVIGATE


async def test_refused_value_is_echoed_old_with_a_statustext() -> None:
    """Each refused value gets the old value back and, a second or more after the last, a STATUSTEXT saying why."""
    async with rig(route=Route.point(20.0, 0.0, -5.0, source="test")) as (svc, ap), gcs_for(svc) as gcs:
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 3, 10.0, "flying")
        old_planner = svc.navigator.planner
        seen: list[Any] = []
        apart = int(REFUSED_INTERVAL_S / TICK_S) + 1  # autopilot ticks: the service clock follows them
        msg = await set_param(gcs, "APF_CRUISE_SPD", -1.0, seen)  # cycle.cruise_speed_m_s must be in (0, 20]
        assert msg.param_value == pytest.approx(1.0)
        await ap.ticks_pass(apart)
        msg = await set_param(gcs, "APF_N_BACT", 2.5, seen)  # an integer parameter
        assert msg.param_value == pytest.approx(PlannerParams().n_bacteria)
        await ap.ticks_pass(apart)
        msg = await set_param(gcs, "APF_RHO_U", math.nan, seen)
        assert msg.param_value == pytest.approx(PlannerParams().rho_u_m)
        texts = [m.text for m in seen if m.get_type() == "STATUSTEXT"]
        while sum("refused" in t for t in texts) < 3:
            st = await gcs.recv_match(type="STATUSTEXT", timeout=5.0)
            texts.append(st.text)
        joined = " ".join(texts)
        assert "APF_CRUISE_SPD refused" in joined and "APF_N_BACT refused" in joined
        assert svc.navigator.planner is old_planner and svc.params.refused == 3
        # an unknown name gets no answer at all (ArduPilot and PX4 stay silent)
        gcs.send(gcs.mav.param_set_encode(1, 191, b"APF_NOGOOD", 1.0, mavlink.MAV_PARAM_TYPE_REAL32))
        gcs.send(gcs.mav.param_request_read_encode(1, 191, b"APF_STEP", -1))
        msg = (await param_values(gcs, 1))[0]
        assert msg.param_id == "APF_STEP"


def test_refusals_are_said_at_once_then_at_most_once_a_second(caplog: pytest.LogCaptureFixture) -> None:
    """A review sent 300 refused PARAM_SETs (APF_STEP = -1) in 0.65 s: 900 STATUSTEXT chunks towards the autopilot
    and 300 WARNING lines. Now the first refusal is said at once (STATUSTEXT and WARNING ``param.refused``), then
    at most one of each per ``REFUSED_INTERVAL_S`` of the service clock, carrying how many went unsaid (the others
    go to DEBUG). Driven with the service time, socket-free."""
    cfg = config_from_mapping({})
    texts: list[str] = []
    outbox = Outbox(None, dry_run=False, target_system=1, target_component=1, now_s=lambda: 0.0)
    server = ParamServer(
        cfg,
        planner_params(cfg),
        outbox=outbox,
        apply=lambda *_: None,
        statustext=lambda _, t: texts.append(t),
        counters=ServiceCounters(),
    )
    bad = ParamSet(
        src=Source(255, 190), target_system=1, target_component=191, param_id="APF_STEP", param_value=-1.0,
        param_type=mavlink.MAV_PARAM_TYPE_REAL32,
    )  # fmt: skip

    def warnings() -> list[logging.LogRecord]:
        return [r for r in caplog.records if r.getMessage() == "param.refused" and r.levelno == logging.WARNING]

    caplog.set_level(logging.DEBUG, logger="apf_companion.params")
    t0 = 100.0
    for i in range(300):  # 300 in 0.6 s
        server.handle(bad, t0 + i * 0.002)
    assert len(texts) == 1 and texts[0].startswith("APF_STEP refused: planner.params")
    assert len(warnings()) == 1 and warnings()[0].unlogged == 0  # type: ignore[attr-defined]
    assert sum(r.getMessage() == "param.refused" and r.levelno == logging.DEBUG for r in caplog.records) == 299
    server.handle(bad, t0 + REFUSED_INTERVAL_S)  # a second after the first: said, with the count
    assert len(texts) == 2 and texts[1].startswith("APF_STEP refused (299 more refused, not said): planner.params")
    assert len(warnings()) == 2 and warnings()[1].unlogged == 299  # type: ignore[attr-defined]
    server.handle(bad, t0 + 1.5 * REFUSED_INTERVAL_S)
    assert len(texts) == 2 and len(warnings()) == 2 and server.refused == 302


async def test_a_flood_of_refused_values_gets_every_answer_and_few_texts() -> None:
    """Each refused PARAM_SET is answered with the old value (the ground station sends it again without one, as
    ArduPilot's handle_param_set answers a denied one); STATUSTEXTs about them come at most once a second of the
    service clock, the first at once."""
    async with rig(route=Route.point(20.0, 0.0, -5.0, source="test")) as (svc, ap), gcs_for(svc) as gcs:
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 3, 10.0, "flying")

        def said() -> list[str]:
            return [m.text for m in ap.of_type("STATUSTEXT") if m.text.startswith("APF_STEP refused")]

        t0 = svc.clock.now()
        for _ in range(50):
            gcs.send(gcs.mav.param_set_encode(1, 191, b"APF_STEP", -1.0, mavlink.MAV_PARAM_TYPE_REAL32))
        values = await param_values(gcs, 50)
        span_s = svc.clock.now() - t0  # every PARAM_SET was handled within it
        assert {(v.param_id, round(v.param_value, 6)) for v in values} == {("APF_STEP", PlannerParams().step_m)}
        await within(svc.clock.now, lambda: bool(said()), 2.0, "the first refusal said")
        assert svc.params.refused == 50
        assert 1 <= len(said()) <= 1 + span_s / REFUSED_INTERVAL_S


def _margin(value: float) -> ParamSet:
    return ParamSet(
        src=Source(255, 190), target_system=1, target_component=191, param_id="APF_MARGIN", param_value=value,
        param_type=mavlink.MAV_PARAM_TYPE_REAL32,
    )  # fmt: skip


@dataclass
class _Server:
    """A socket-free ParamServer with what it sent and did: PARAM_VALUEs, STATUSTEXTs, planner builds, applies."""

    server: ParamServer
    answers: list[tuple[str, float]]
    texts: list[str]
    builds: list[ServiceConfig]
    applied: list[ServiceConfig]


def _server(cfg: ServiceConfig, *, refuse_builds: bool = False) -> _Server:
    answers: list[tuple[str, float]] = []
    texts: list[str] = []
    builds: list[ServiceConfig] = []
    applied: list[ServiceConfig] = []
    outbox = Outbox(None, dry_run=False, target_system=1, target_component=1, now_s=lambda: 0.0)
    outbox.param_value = lambda name, value, *_: answers.append((name, value))  # type: ignore[method-assign]

    def build(config: ServiceConfig) -> Any:
        builds.append(config)
        if refuse_builds:
            raise ConfigError("planner.params: refused by the build")
        return build_planner(config)

    server = ParamServer(
        cfg,
        planner_params(cfg),
        outbox=outbox,
        apply=lambda config, _planner: applied.append(config),
        statustext=lambda _, t: texts.append(t),
        counters=ServiceCounters(),
        build=build,
    )
    return _Server(server, answers, texts, builds, applied)


def _param_set_lines(caplog: pytest.LogCaptureFixture, level: int) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.getMessage() == "param.set" and r.levelno == level]


def test_a_flood_of_accepted_values_builds_the_planner_once_a_cycle(caplog: pytest.LogCaptureFixture) -> None:
    """A review's nit: a flood of accepted PARAM_SETs logged each and built the planner each time (bapf-nav:
    ~1.2 ms). Now each is answered with its value at once, the planner is built once per cycle for all those since
    the last, and the INFO line ``param.set`` comes at once, then at most once a second with how many went unlogged.
    300 sets in 0.6 s with cycles at 10 Hz, socket-free on the service time."""
    caplog.set_level(logging.DEBUG, logger="apf_companion.params")
    s = _server(config_from_mapping({}))  # bapf-nav, the planner whose build costs
    values = [round(0.1 + 0.001 * i, 3) for i in range(300)]
    t0 = 100.0
    for i, value in enumerate(values):
        s.server.handle(_margin(value), t0 + i * 0.002)
        if i % 50 == 49:  # a cycle every 0.1 s
            assert s.server.apply_pending()
    assert s.answers == [("APF_MARGIN", v) for v in values]  # every one answered with the value in force
    assert len(s.builds) == len(s.applied) == 6 and s.server.builds == 6
    assert [c.planner.params["safety_margin_m"] for c in s.applied] == values[49::50]
    assert s.server.counters.param_sets_coalesced == 294 and s.server.sets == 300
    assert not s.server.apply_pending() and len(s.builds) == 6  # nothing pending: no build
    infos = _param_set_lines(caplog, logging.INFO)
    assert len(infos) == 1 and infos[0].new == 0.1 and infos[0].unlogged == 0  # type: ignore[attr-defined]
    assert len(_param_set_lines(caplog, logging.DEBUG)) == 299
    s.server.handle(_margin(0.05), t0 + SET_LOG_INTERVAL_S)  # a second after the first: logged, with the count
    infos = _param_set_lines(caplog, logging.INFO)
    assert len(infos) == 2 and infos[1].unlogged == 299 and infos[1].new == 0.05  # type: ignore[attr-defined]


def test_one_accepted_value_is_logged_at_once_and_in_service_at_the_next_cycle(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="apf_companion.params")
    cfg = config_from_mapping({})
    s = _server(cfg)
    margin0 = planner_params(cfg).safety_margin_m
    s.server.handle(_margin(0.3), 100.0)
    assert s.answers == [("APF_MARGIN", 0.3)] and s.server.planner_params.safety_margin_m == 0.3
    infos = _param_set_lines(caplog, logging.INFO)
    assert [(r.param, r.old, r.new) for r in infos] == [("APF_MARGIN", margin0, 0.3)]  # type: ignore[attr-defined]
    assert not s.applied  # not before the next cycle
    assert s.server.apply_pending()
    assert len(s.applied) == 1 and s.applied[0].planner.params["safety_margin_m"] == 0.3
    assert s.server.counters.param_sets_coalesced == 0
    s.server.handle(_margin(0.3), 102.0)  # the value in force: answered and logged, nothing to build
    assert s.answers[-1] == ("APF_MARGIN", 0.3) and len(_param_set_lines(caplog, logging.INFO)) == 2
    assert not s.server.apply_pending() and len(s.builds) == 1
    assert s.server.counters.param_sets_coalesced == 1


def test_changes_that_cannot_be_built_are_undone_and_said() -> None:
    """Not expected (``planner_params`` checks what the planners check), but a planner build that fails keeps the
    values in service and tells the ground station: PARAM_VALUE with the value in force, and a STATUSTEXT."""
    cfg = config_from_mapping({})
    s = _server(cfg, refuse_builds=True)
    margin0 = planner_params(cfg).safety_margin_m
    s.server.handle(_margin(0.3), 100.0)
    assert not s.server.apply_pending() and not s.applied
    assert s.answers == [("APF_MARGIN", 0.3), ("APF_MARGIN", margin0)]
    assert s.texts == ["params not applied: planner.params: refused by the build"]
    assert s.server.config is cfg and s.server.planner_params.safety_margin_m == margin0
    assert not s.server.apply_pending() and len(s.builds) == 1  # nothing pending any more


async def test_a_flood_of_accepted_values_over_loopback_is_answered_and_built_once_a_cycle(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """100 accepted PARAM_SETs at once from a ground station while flying: 100 PARAM_VALUEs with the values set, at
    most one planner build (and navigator reconfiguration) per cycle, the last value in service, and the
    ``param.set`` INFO lines at most once a second. On the old code each set rebuilt and logged: 100 of each."""
    caplog.set_level(logging.INFO, logger="apf_companion.params")
    async with rig(route=Route.point(20.0, 0.0, -5.0, source="test")) as (svc, ap), gcs_for(svc) as gcs:
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 3, 10.0, "flying")
        nav = svc.navigator
        reconfigure = nav.reconfigure
        reconfigured: list[int] = []

        def counting(params: NavigatorParams, planner: Any) -> None:
            reconfigured.append(nav.counters.cycles)
            reconfigure(params, planner)

        nav.reconfigure = counting  # type: ignore[method-assign]
        values = [round(0.1 + 0.002 * i, 3) for i in range(100)]
        cycles0, t0 = nav.counters.cycles, svc.clock.now()
        for value in values:
            gcs.send(gcs.mav.param_set_encode(1, 191, b"APF_MARGIN", value, mavlink.MAV_PARAM_TYPE_REAL32))
        answers = await param_values(gcs, len(values))
        span_s = svc.clock.now() - t0
        await next_cycle(svc)
        assert [a.param_value for a in answers] == pytest.approx(values)
        assert svc.planner.params.safety_margin_m == values[-1]
        assert 1 <= len(reconfigured) <= nav.counters.cycles - cycles0  # old code: 100
        assert svc.counters.param_sets_coalesced == len(values) - len(reconfigured)
        assert svc.reporter.counts()["param_sets_coalesced"] == svc.counters.param_sets_coalesced
        infos = _param_set_lines(caplog, logging.INFO)
        assert 1 <= len(infos) <= 1 + span_s / SET_LOG_INTERVAL_S  # old code: 100


async def test_apf_fence_poll_sets_how_often_the_running_service_reads_the_fence() -> None:
    async with rig() as (svc, _ap), gcs_for(svc) as gcs:
        assert svc.fence is not None and svc.fence.params.poll_s == 5.0  # bapf-nav, no area: the fence is read
        msg = await set_param(gcs, "APF_FENCE_POLL", 0.0)  # 0: read once
        await next_cycle(svc)
        assert msg.param_value == 0.0 and svc.fence.params.poll_s == 0.0
        msg = await set_param(gcs, "APF_FENCE_POLL", 0.5)  # refused: 0, or 1-3600 s
        await next_cycle(svc)
        assert msg.param_value == 0.0 and svc.fence.params.poll_s == 0.0
        msg = await set_param(gcs, "APF_FENCE_POLL", 30.0)
        await next_cycle(svc)
        assert msg.param_value == 30.0 and svc.fence.params.poll_s == 30.0
        assert svc.params.sets == 2 and svc.params.refused == 1


def test_config_with_validates_like_the_toml_file() -> None:
    cfg = config_from_mapping({"planner": {"name": "cr-bapf*"}})
    planner = CompanionService(cfg).planner
    by_name = {p.name: p for p in PARAMS}
    new, new_params = config_with(cfg, planner.params, by_name["APF_MARGIN"], 0.25)
    assert new.planner.params["safety_margin_m"] == 0.25 and new_params.safety_margin_m == 0.25
    new, _ = config_with(cfg, planner.params, by_name["APF_RESUME_LINK"], 0.0)
    assert new.safety.resume_after_link_lost is False
    for name, bad, says in (
        ("APF_RESUME_LINK", 2.0, "0 or 1"),
        ("APF_SILENT_DRIFT", 11.0, "safety.silent_drift_m"),
        ("APF_RHO_L", 10.0, "rho_l"),  # the planner's own check: rho_l < rho_u
        ("APF_RW_BUDGET", 0.0, "planner.random_walk_budget"),
    ):
        with pytest.raises(ValueError, match=says):
            config_with(cfg, planner.params, by_name[name], bad)


@pytest.mark.skipif(mavproxy_path() is None, reason="MAVProxy not installed (pip install --no-deps MAVProxy)")
async def test_mavproxy_param_module_fetches_and_sets(tmp_path: Path) -> None:
    """MAVProxy's own param module, typed at its prompt: fetch the list, set a value, have one refused."""
    mavproxy = mavproxy_path()
    assert mavproxy is not None
    async with rig(route=Route.point(30.0, 0.0, -5.0, source="test")) as (svc, _ap):
        assert svc.link is not None and svc.link.local_address is not None
        master = f"udpout:127.0.0.1:{svc.link.local_address[1]}"
        async with mavproxy_session(mavproxy, master, "191", tmp_path) as gcs:
            await gcs.read_until("Detected vehicle 1:191")
            gcs.type_in("set param_ftp false")  # no MAVLink FTP here: the plain PARAM_REQUEST_LIST
            gcs.type_in("param fetch")
            await gcs.read_until(f"Received {len(PARAMS)} parameters")
            gcs.type_in("param set APF_CRUISE_SPD 0.5")
            await until(lambda: svc.navigator.params.cruise_speed_m_s == 0.5, HANG_S, "set by MAVProxy")
            gcs.type_in("param set APF_RHO_L 9")
            await gcs.read_until("APF_RHO_L refused")
        assert svc.params.sets == 1 and svc.params.refused == 1
        assert svc.params.planner_params.rho_l_m == svc.planner.params.rho_l_m == PlannerParams().rho_l_m
