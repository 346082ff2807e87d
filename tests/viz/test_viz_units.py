"""The Foxglove output's pieces without a flight: frames, scores, config and CLI, the shipped layout, bad input."""

from __future__ import annotations

import datetime
import json
import math
import socket
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from apf_companion.cli import _effective_config, build_parser
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.errors import ConfigError
from apf_companion.observe import PlanStep
from apf_companion.planning import BapfNavPlanner, Decision, DecisionReason, PlannerParams
from apf_companion.service import CompanionService
from apf_companion.viz import FRAME_ENU, FRAME_NED, NED_IN_ENU_XYZW, Topic, yaw_quaternion_xyzw
from apf_companion.viz.scene import candidate_scores
from apf_companion.viz.sink import FoxgloveSink, mcap_path_in

LAYOUT = Path(__file__).resolve().parents[2] / "deploy" / "foxglove" / "apf-companion-layout.json"


def _rotate(q: tuple[float, float, float, float], v: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """v rotated by the unit quaternion q = (x, y, z, w)."""
    x, y, z, w = q
    u = np.array([x, y, z])
    return np.asarray(v + 2.0 * np.cross(u, np.cross(u, v) + w * v))


def test_ned_in_enu_swaps_north_east_and_flips_down() -> None:
    ned = np.array([1.0, 2.0, 3.0])  # 1 m north, 2 m east, 3 m down
    assert _rotate(NED_IN_ENU_XYZW, ned) == pytest.approx([2.0, 1.0, -3.0])
    assert (FRAME_NED, FRAME_ENU) == ("ned", "enu")


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, -45.0, 180.0])
def test_yaw_quaternion_turns_the_nose_clockwise_from_north(yaw_deg: float) -> None:
    yaw = math.radians(yaw_deg)
    nose = _rotate(yaw_quaternion_xyzw(yaw), np.array([1.0, 0.0, 0.0]))  # body forward, in NED
    assert nose == pytest.approx([math.cos(yaw), math.sin(yaw), 0.0], abs=1e-12)


def _plan(decision: Decision, n: int) -> PlanStep:
    return PlanStep(seq=1, origin_m=np.zeros(2), target_m=np.ones(2), candidates_m=np.zeros((n, 2)), decision=decision)


def test_candidate_scores_rank_the_passing_points_and_mark_the_rest() -> None:
    cost = np.array([3.0, np.inf, 1.0, 2.0])
    d = Decision(next_point_m=np.zeros(2), reason=DecisionReason.GREEDY, chosen_index=2, candidate_cost=cost)
    score, cost_m = candidate_scores(_plan(d, 4))
    assert score.tolist() == [0.0, -1.0, 1.0, 0.5]
    assert np.isnan(cost_m[1]) and cost_m[[0, 2, 3]].tolist() == [3.0, 1.0, 2.0]
    blocked = Decision(next_point_m=None, reason=DecisionReason.LOCAL_MINIMUM, candidate_cost=np.full(4, np.inf))
    assert candidate_scores(_plan(blocked, 4))[0].tolist() == [-1.0] * 4
    unscored = Decision(next_point_m=None, reason=DecisionReason.LOCAL_MINIMUM)  # planners without scores
    assert candidate_scores(_plan(unscored, 4))[0].tolist() == [0.0] * 4


def test_bapf_nav_reports_a_score_per_candidate_and_chooses_a_passing_one() -> None:
    planner = BapfNavPlanner(PlannerParams())
    d = planner.step(np.zeros(2), np.array([10.0, 0.0]), np.array([[1.0, 0.0], [1.0, 0.3], [1.0, -0.3]]))
    assert d.candidate_cost is not None and d.candidate_cost.shape == (planner.params.n_bacteria,)
    assert d.chosen_index is not None and math.isfinite(d.candidate_cost[d.chosen_index])
    assert d.n_passing == int(np.isfinite(d.candidate_cost).sum())


def test_visualisation_config_and_bad_values() -> None:
    cfg = config_from_mapping({"visualisation": {"foxglove": True, "foxglove_port": 0, "mcap_dir": "rec"}})
    assert cfg.visualisation.enabled and cfg.visualisation.foxglove_port == 0
    assert not ServiceConfig().visualisation.enabled
    with pytest.raises(ConfigError, match=r"visualisation\.foxglove_port"):
        config_from_mapping({"visualisation": {"foxglove_port": 70000}})
    with pytest.raises(ConfigError, match=r"visualisation\.foxglove"):
        config_from_mapping({"visualisation": {"foxglove": "yes"}})


def test_run_flags_turn_the_outputs_on(tmp_path: Path) -> None:
    args = build_parser().parse_args(["run", "--foxglove", "--mcap-dir", str(tmp_path)])
    cfg, _ = _effective_config(args)
    assert cfg.visualisation.foxglove and cfg.visualisation.foxglove_port == 8765
    assert cfg.visualisation.mcap_dir == str(tmp_path.resolve())
    cfg, _ = _effective_config(build_parser().parse_args(["run", "--foxglove", "0"]))
    assert cfg.visualisation.foxglove_port == 0 and not cfg.visualisation.mcap_dir
    with pytest.raises(ConfigError, match="foxglove_port"):
        _effective_config(build_parser().parse_args(["run", "--foxglove", "99999"]))


def test_each_run_gets_its_own_recording(tmp_path: Path) -> None:
    now = datetime.datetime(2026, 1, 2, 3, 4, 5, tzinfo=datetime.UTC)
    first = mcap_path_in(tmp_path, now)
    assert first.name == "apf-20260102T030405Z.mcap"
    first.write_bytes(b"")
    assert mcap_path_in(tmp_path, now).name == "apf-20260102T030405Z-1.mcap"


def test_sink_refuses_bad_outputs_with_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="MCAP path or a port"):
        FoxgloveSink()
    taken = tmp_path / "taken.mcap"
    taken.write_bytes(b"x")
    with pytest.raises(ConfigError, match="cannot open the Foxglove output"):
        FoxgloveSink(mcap_path=taken)  # never overwrites a recording
    assert taken.read_bytes() == b"x"


def test_a_taken_port_or_a_missing_sdk_is_a_config_error(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=f"127.0.0.1:{port}"):
            FoxgloveSink(port=port)
    # As if the viz extra were not installed: the service refuses the config, it does not crash.
    monkeypatch.setitem(sys.modules, "foxglove", None)
    for name in ("apf_companion.viz.sink", "apf_companion.viz.scene"):
        monkeypatch.delitem(sys.modules, name)
    cfg = config_from_mapping({"visualisation": {"foxglove": True, "foxglove_port": 0}})
    with pytest.raises(ConfigError, match=r"apf-companion\[viz\]"):
        CompanionService(cfg)


def test_the_shipped_layout_shows_only_topics_the_service_publishes() -> None:
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    configs = layout["configById"]
    three = next(v for k, v in configs.items() if k.startswith("3D!"))
    assert three["followTf"] == FRAME_ENU
    topics = set(three["topics"])
    for key, cfg in configs.items():
        for path in cfg.get("paths", []):
            topics.add(path["value"].split(".")[0])
        if key.startswith("RosOut!"):
            topics.add(cfg["topicToRender"])
        if "topicPath" in cfg:
            topics.add(cfg["topicPath"])
    published = {str(t) for t in Topic}
    assert topics <= published, topics - published
    assert {Topic.POSE, Topic.OBSTACLES, Topic.SCAN, Topic.CANDIDATES, Topic.SCENE, Topic.LOG, Topic.CYCLE} <= topics
    assert three["topics"][Topic.CANDIDATES]["colorField"] == "score"
    panels = {k.split("!")[0] for k in configs}
    assert {"3D", "RosOut", "Plot", "StateTransitions"} <= panels
    assert set(_leaves(layout["layout"])) == set(configs)


def _leaves(node: Any) -> list[str]:
    return [node] if isinstance(node, str) else _leaves(node["first"]) + _leaves(node["second"])
