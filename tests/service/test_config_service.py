"""The service config: defaults, strict TOML loading, errors that name the key and the range."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from apf_companion.autopilot import Autopilot
from apf_companion.builders import navigator_params
from apf_companion.config import ServiceConfig, config_from_mapping, load_config
from apf_companion.errors import ConfigError
from apf_companion.service import build_planner, initial_route

REPO = Path(__file__).resolve().parents[2]


def test_defaults_are_documented_values() -> None:
    cfg = ServiceConfig()
    assert cfg.cycle.rate_hz == 10.0
    assert cfg.cycle.pose_max_age_s == 0.5 and cfg.cycle.ranges_max_age_s == 0.5
    assert cfg.link.component_id == 191
    assert cfg.link.heartbeat_timeout_s == 3.0
    assert cfg.autopilot.profile is Autopilot.ARDUPILOT
    assert cfg.autopilot.arm is False and cfg.autopilot.takeoff_alt_m == 0.0
    assert cfg.dry_run is False
    assert cfg.planner.name == "bapf-nav"


def test_deploy_example_loads_and_builds_its_planner() -> None:
    cfg = load_config(REPO / "deploy" / "apf-companion.toml")
    planner = build_planner(cfg)
    assert planner is not None
    # The example's values are the defaults it documents (the file is a commented copy of them).
    assert cfg.cycle == ServiceConfig().cycle


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"cycle": {"rate_hz": 80.0}}, r"cycle\.rate_hz must be in \[1\.0, 50\.0\]"),
        ({"cycle": {"rate_hz": math.nan}}, r"cycle\.rate_hz"),
        ({"cycle": {"pose_max_age_s": 0.0}}, r"cycle\.pose_max_age_s"),
        ({"link": {"component_id": 190}}, r"link\.component_id"),
        ({"link": {"component_id": 300}}, r"link\.component_id must be an integer in \[1, 255\]"),
        # the autopilot's own ids (we send with its sysid): a review's config passed with component_id = 1
        ({"link": {"component_id": 1}}, r"link\.component_id must be different from link\.autopilot_compid"),
        ({"link": {"autopilot_compid": 191}}, r"link\.component_id must be different from link\.autopilot_compid"),
        ({"link": {"gcs_sysids": [1]}}, r"link\.gcs_sysids"),
        ({"autopilot": {"profile": "inav"}}, r"autopilot\.profile must be one of 'ardupilot', 'px4'"),
        ({"autopilot": {"offboard_prestream_s": 0.5}}, r"autopilot\.offboard_prestream_s"),
        ({"planner": {"name": "apf"}}, r"planner\.name must be one of"),
        ({"planner": {"dim": 4}}, r"planner\.dim must be 2 or 3"),
        ({"zenoh": {"enabled": True}}, r"zenoh\.connect/zenoh\.listen"),
        ({"zenoh": {"connect": ["udp/127.0.0.1:7447"]}}, r"zenoh\.connect\[\] must be an explicit"),
        ({"sensors": {"zenoh": True}}, r"sensors\.zenoh"),
        ({"goal": {"north_m": 1.0}}, r"goal\.north_m/goal\.east_m"),
        ({"goal": {"min_altitude_m": -20_000.0}}, r"goal\.min_altitude_m must be in \[-10000\.0, 10000\.0\]"),
        ({"goal": {"min_altitude_m": math.nan}}, r"goal\.min_altitude_m must be in"),
        ({"goal": {"min_altitude_m": 120.0}}, r"goal\.min_altitude_m must be less than goal\.max_altitude_m"),
        ({"cycle": {"rate_hz": "fast"}}, r"cycle\.rate_hz must be a number"),
        ({"dry_run": "yes"}, r"dry_run must be true or false"),
        ({"max_link_lost_s": -1.0}, r"max_link_lost_s must be in \[0\.0, 86400\.0\]"),
        ({"max_link_lost_s": "long"}, r"max_link_lost_s must be a number"),
        ({"max_link_lost_s": 2.0}, r"max_link_lost_s must be 0 or at least link\.heartbeat_timeout_s, got 2\.0"),
    ],
)
def test_bad_values_name_the_key(table: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        config_from_mapping(table)


def test_the_altitude_floor_defaults_to_1_m_and_may_go_below_home() -> None:
    """``goal.min_altitude_m``: 1 m above home by default; negative (a valley below the take-off point) and, with
    ``max_altitude_m`` 0 (no ceiling), any value in its range are valid."""
    assert ServiceConfig().goal.min_altitude_m == 1.0
    assert config_from_mapping({"goal": {"min_altitude_m": -300}}).goal.min_altitude_m == -300.0
    assert config_from_mapping({"goal": {"min_altitude_m": 500.0, "max_altitude_m": 0.0}}).goal.min_altitude_m == 500


def test_typo_gets_a_suggestion() -> None:
    with pytest.raises(ConfigError, match=r"unknown config key 'cycle\.rate_hzz'; did you mean 'rate_hz'"):
        config_from_mapping({"cycle": {"rate_hzz": 10}})
    with pytest.raises(ConfigError, match=r"unknown config key 'cylce'; did you mean 'cycle'"):
        config_from_mapping({"cylce": {}})
    typo = config_from_mapping({"planner": {"params": {"vehicle_radus_m": 0.3}}})
    match = r"unknown planner parameter planner\.params\.vehicle_radus_m; did you mean 'vehicle_radius_m'\? \(allowed"
    with pytest.raises(ConfigError, match=match):
        build_planner(typo)
    with pytest.raises(ConfigError) as far:  # nothing close: no guess, only the list
        build_planner(config_from_mapping({"planner": {"params": {"zzz": 1}}}))
    assert "did you mean" not in str(far.value) and "allowed: " in str(far.value)


def test_ints_become_floats_and_lists_tuples() -> None:
    cfg = config_from_mapping({"cycle": {"rate_hz": 20}, "link": {"gcs_sysids": [255, 250]}})
    assert cfg.cycle.rate_hz == 20.0 and isinstance(cfg.cycle.rate_hz, float)
    assert cfg.link.gcs_sysids == (255, 250)


def test_planner_params_overrides_and_errors() -> None:
    cfg = config_from_mapping(
        {"planner": {"name": "a-bapf", "dim": 3, "params": {"step_m": 0.3, "abapf_rule": "paper", "mu_max": 500}}}
    )
    planner = build_planner(cfg)
    assert planner.params.step_m == 0.3 and planner.params.dim == 3
    assert planner.params.abapf_rule.value == "paper"
    with pytest.raises(ConfigError, match=r"planner\.params\.step"):
        build_planner(config_from_mapping({"planner": {"params": {"step": 0.3}}}))
    with pytest.raises(ConfigError, match=r"planner\.params\.random_walk must be one of"):
        build_planner(config_from_mapping({"planner": {"params": {"random_walk": "drunk"}}}))
    with pytest.raises(ConfigError, match=r"rho_u_m"):
        build_planner(config_from_mapping({"planner": {"params": {"rho_u_m": 0.1}}}))
    area = build_planner(config_from_mapping({"planner": {"params": {"nav_area_ne_m": [-3, -12.0, 23, 12]}}}))
    assert area.params.nav_area_ne_m == (-3.0, -12.0, 23.0, 12.0)  # a list of numbers: a vector parameter
    with pytest.raises(ConfigError, match=r"planner\.params\.nav_area_ne_m.*list of numbers"):
        config_from_mapping({"planner": {"params": {"nav_area_ne_m": [0, "a", 1, 2]}}})
    with pytest.raises(ConfigError, match=r"nav_area_ne_m"):
        build_planner(config_from_mapping({"planner": {"params": {"nav_area_ne_m": [0, 0, 1]}}}))


def test_a_configured_goal_outside_the_flying_area_is_a_config_error() -> None:
    """bapf-nav gives up at once on a target outside ``nav_area_ne_m``: a configured goal there is refused when
    the config is loaded (``apf-companion check-config``, the service's start), not after take-off; other planners have
    no area."""
    area = {"nav_area_ne_m": [-3.0, -12.0, 23.0, 12.0]}
    inside = config_from_mapping({"planner": {"params": area}, "goal": {"north_m": 20.0, "east_m": 0.0}})
    assert initial_route(inside, build_planner(inside)) is not None
    outside = config_from_mapping({"planner": {"params": area}, "goal": {"north_m": 30.0, "east_m": 0.0}})
    with pytest.raises(ConfigError, match=r"waypoint 0 .*outside the flying area planner\.params\.nav_area_ne_m"):
        initial_route(outside, build_planner(outside))
    other = config_from_mapping(
        {"planner": {"name": "cr-bapf*", "params": area}, "goal": {"north_m": 30.0, "east_m": 0.0}}
    )
    assert initial_route(other, build_planner(other)) is not None


def test_a_polygonal_flying_area_from_a_config_file() -> None:
    """``nav_area_ne_m = [[north, east], ...]`` (TOML) is a polygon: the planner keeps it, and a configured goal in
    its notch (inside its bounds, outside the polygon) is refused with the polygon written as in the file."""
    text = """
[planner.params]
nav_area_ne_m = [[-3.0, -3.0], [23.0, -3.0], [23.0, 6.0], [9.0, 6.0], [9.0, 23.0], [-3.0, 23.0]]
[goal]
north_m = 2.0
east_m = 20.0
"""
    config = config_from_mapping(tomllib.loads(text))
    planner = build_planner(config)
    assert planner.params.nav_area_ne_m == (
        (-3.0, -3.0),
        (23.0, -3.0),
        (23.0, 6.0),
        (9.0, 6.0),
        (9.0, 23.0),
        (-3.0, 23.0),
    )
    assert initial_route(config, planner) is not None
    notch = config_from_mapping(tomllib.loads(text.replace("north_m = 2.0", "north_m = 15.0")))
    with pytest.raises(ConfigError, match=r"waypoint 0 .*nav_area_ne_m = \[\[-3.0, -3.0\], \[23.0, -3.0\]"):
        initial_route(notch, build_planner(notch))
    for bad in ([[0, 0], [10, "a"], [10, 10]], [[0, 0], [10, [1]], [10, 10]], [[0, 0], 10, [10, 10]]):
        with pytest.raises(ConfigError, match=r"planner\.params\.nav_area_ne_m.*list of numbers \(or of such lists"):
            config_from_mapping({"planner": {"params": {"nav_area_ne_m": bad}}})
    with pytest.raises(ConfigError, match=r"nav_area_ne_m.*edges that do not cross"):  # a bow tie
        build_planner(
            config_from_mapping({"planner": {"params": {"nav_area_ne_m": [[0, 0], [9, 9], [9, 0], [0, 12]]}}})
        )


def test_keep_out_zones_from_a_config_file() -> None:
    """``nav_keepout_ne_m = [[[north, east], ...], ...]`` (TOML, three lists deep): the planner keeps them, a goal in
    one is refused at load, and the service reads no fence (the config's zones win)."""
    text = """
[planner.params]
nav_keepout_ne_m = [[[7.0, -3.0], [13.0, -3.0], [13.0, 3.0], [7.0, 3.0]], [[20.0, 5.0], [22.0, 5.0], [21.0, 7.0]]]
[goal]
north_m = 20.0
east_m = 0.0
"""
    config = config_from_mapping(tomllib.loads(text))
    planner = build_planner(config)
    assert len(planner.params.nav_keepout_ne_m) == 2 and planner.params.nav_keepout_ne_m[1][2] == (21.0, 7.0)
    assert initial_route(config, planner) is not None
    inside = config_from_mapping(tomllib.loads(text.replace("north_m = 20.0", "north_m = 10.0")))
    with pytest.raises(
        ConfigError, match=r"waypoint 0 .*lies in keep-out zone 0 \(planner\.params\.nav_keepout_ne_m\)"
    ):
        initial_route(inside, build_planner(inside))
    with pytest.raises(ConfigError, match=r"planner\.params\.nav_keepout_ne_m.*list of numbers \(or of such lists"):
        config_from_mapping({"planner": {"params": {"nav_keepout_ne_m": [[[[0, 0]]]]}}})  # four deep
    with pytest.raises(ConfigError, match=r"nav_keepout_ne_m.*up to 16 polygons"):
        build_planner(config_from_mapping({"planner": {"params": {"nav_keepout_ne_m": [[[0, 0], [1, 1]]]}}}))


def test_load_config_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot read config file"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[cycle\nrate_hz = 1\n")
    with pytest.raises(ConfigError, match=r"not valid TOML"):
        load_config(bad)


def test_route_file_resolves_against_config_dir(tmp_path: Path) -> None:
    (tmp_path / "route.csv").write_text("north,east,down\n1,2,-3\n4,5\n")
    cfgfile = tmp_path / "c.toml"
    cfgfile.write_text('[goal]\nroute = "route.csv"\n')
    cfg = load_config(cfgfile)
    route = initial_route(cfg, build_planner(cfg))
    assert route is not None and len(route) == 2
    assert route.waypoints_ned_m[0].tolist() == [1.0, 2.0, -3.0]
    assert math.isnan(route.waypoints_ned_m[1, 2])


def test_example_toml_is_valid_toml_with_every_section() -> None:
    data = tomllib.loads((REPO / "deploy" / "apf-companion.toml").read_text())
    assert {"link", "autopilot", "planner", "cycle", "sensors", "zenoh", "status"} <= set(data)


@pytest.mark.parametrize("name", ["apf-companion.toml", "apf-companion-px4-zenoh.toml"])
def test_every_deploy_example_is_valid(name: str) -> None:
    cfg = load_config(REPO / "deploy" / name)
    build_planner(cfg)


def test_route_example_loads() -> None:
    from apf_companion.goal import load_route

    route = load_route(REPO / "deploy" / "route-example.toml")
    assert len(route) == 3 and math.isnan(route.waypoints_ned_m[1, 2])


def test_sensor_sources_and_forwarding_keys() -> None:
    cfg = config_from_mapping(
        {"sensors": {"mavlink_sources": ["1/158", "2/196"], "forward_obstacle_distance": True, "forward_rate_hz": 20}}
    )
    assert cfg.sensors.source_ids() == ((1, 158), (2, 196))
    assert cfg.sensors.forward_obstacle_distance and cfg.sensors.forward_rate_hz == 20.0
    defaults = config_from_mapping({})
    assert defaults.sensors.mavlink_sources == () and not defaults.sensors.forward_obstacle_distance
    bad_sources: list[object] = ["1-158", "1/0", "256/1", "1/", "a/b", "1/158/2"]
    for bad in bad_sources:
        with pytest.raises(ConfigError, match=r"sensors\.mavlink_sources\[\]"):
            config_from_mapping({"sensors": {"mavlink_sources": [bad]}})
    with pytest.raises(ConfigError, match=r"sensors\.mavlink_sources"):
        config_from_mapping({"sensors": {"mavlink_sources": "1/158"}})  # a list, not a string
    for ours in ("1/191", "1/1"):  # our own ids, the autopilot's
        with pytest.raises(ConfigError, match="not our own or the autopilot's ids"):
            config_from_mapping({"sensors": {"mavlink_sources": [ours]}})
    with pytest.raises(ConfigError, match=r"empty unless sensors\.mavlink is true"):
        config_from_mapping({"sensors": {"mavlink": False, "mavlink_sources": ["1/158"]}})
    for rate in (2.0, 60.0):  # below 2.5 Hz ArduPilot's 0.5 s proximity timeout would flicker
        with pytest.raises(ConfigError, match=r"sensors\.forward_rate_hz"):
            config_from_mapping({"sensors": {"forward_rate_hz": rate}})


def test_every_error_in_a_file_is_reported_at_once(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(
        "dry_run = 'yes'\n"
        "[cycle]\nrate_hz = 500\ncruise_speed_m_s = -1\n"
        "[link]\nconect = 'udpin:127.0.0.1:14540'\n"
        "[goal]\nnorth_m = 5.0\neast_m = 1.0\nadopt_tolerance_m = 0\n"
        "[safety]\nsectors = 2\n"
    )
    with pytest.raises(ConfigError) as exc:
        load_config(bad)
    text = str(exc.value)
    assert text.startswith("6 config errors:")
    for key in ("dry_run", "cycle.rate_hz", "cycle.cruise_speed_m_s", "'link.conect'", "goal.adopt_tolerance_m"):
        assert key in text, key
    assert "safety.sectors" in text and "did you mean 'connect'" in text
    assert "goal.north_m/goal.east_m" not in text  # a key checked alone is not blamed for a rule about two keys


def test_a_cross_key_rule_is_still_reported() -> None:
    with pytest.raises(ConfigError, match=r"^goal.north_m/goal.east_m must be both set"):
        config_from_mapping({"goal": {"north_m": 5.0}})


def test_every_planner_parameter_error_is_reported_at_once() -> None:
    cfg = config_from_mapping(
        {"planner": {"params": {"step_m": -1.0, "n_bacteria": 0, "rho_l_m": 5.0, "rho_u_m": 6.0, "nope": 1}}}
    )
    with pytest.raises(ConfigError) as exc:
        build_planner(cfg)
    text = str(exc.value)
    assert text.startswith("3 config errors:"), text
    assert "planner.params.nope" in text and "PlannerParams.step_m" in text and "PlannerParams.n_bacteria" in text
    assert "PlannerParams.rho_" not in text  # rho_l 5 with rho_u 6 is valid together: not blamed


@pytest.mark.parametrize(
    ("profile", "yaw", "travel"),
    [
        ("px4", "auto", True),
        ("ardupilot", "auto", False),
        ("px4", "none", False),
        ("ardupilot", "travel", True),
        ("px4", "travel", True),
    ],
)
def test_autopilot_yaw_resolves_auto_by_profile(profile: str, yaw: str, travel: bool) -> None:
    cfg = config_from_mapping({"autopilot": {"profile": profile, "yaw": yaw}})
    assert cfg.autopilot.yaw_travel is travel
    assert navigator_params(cfg, build_planner(cfg)).yaw_travel is travel


def test_autopilot_yaw_defaults_to_auto_and_rejects_typos() -> None:
    assert ServiceConfig().autopilot.yaw == "auto"
    with pytest.raises(ConfigError, match=r"autopilot\.yaw must be one of 'auto', 'travel', 'none', got 'travle'; did"):
        config_from_mapping({"autopilot": {"yaw": "travle"}})
    with pytest.raises(ConfigError, match=r"autopilot\.yaw must be one of .*got 'None'; did you mean 'none'\?"):
        config_from_mapping({"autopilot": {"yaw": "None"}})
    with pytest.raises(ConfigError, match=r"autopilot\.yaw must be a string, got 1"):
        config_from_mapping({"autopilot": {"yaw": 1}})
    with pytest.raises(ConfigError, match=r"unknown config key 'autopilot\.yow'; did you mean 'yaw'"):
        config_from_mapping({"autopilot": {"yow": "none"}})
