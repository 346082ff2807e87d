"""PlannerParams: paper defaults, presets, and a ConfigError naming the field for every invalid value."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest

from apf_companion.errors import ConfigError
from apf_companion.planning import (
    PLANNER_NAMES,
    AbapfRule,
    AbapfSearch,
    PlannerParams,
    RandomWalkRule,
    get_planner,
)


def test_defaults_are_the_paper_table() -> None:
    p = PlannerParams()
    assert (p.alpha_t, p.mu_t_per_m2, p.alpha_o, p.mu_o_per_m2) == (1e4, 1.0, 1.0, 1000.0)
    assert (p.rho_l_m, p.rho_u_m, p.step_m, p.n_bacteria) == (0.4, 4.5, 0.4, 60)
    assert (p.mu_min, p.mu_max) == (1, 1000)
    assert p.abapf_rule is AbapfRule.EXACT and p.abapf_search is AbapfSearch.GRID
    assert p.random_walk is RandomWalkRule.SAFE_SET and p.agent_repulsion is True
    assert (p.capf_k_att, p.capf_eta, p.capf_rho_0_m, p.dim) == (1.0, 100.0, 3.0, 2)


def test_presets() -> None:
    assert PlannerParams.paper() == PlannerParams()
    ref = PlannerParams.reference()
    assert ref.alpha_t == 1e5
    assert ref.agent_repulsion is False
    assert ref.random_walk is RandomWalkRule.SINGLE_DRAW
    assert PlannerParams.reference(dim=3).dim == 3
    assert dataclasses.replace(ref, mu_o_per_m2=500.0).mu_o_per_m2 == 500.0


def test_frozen() -> None:
    p = PlannerParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.step_m = 1.0  # type: ignore[misc]


BAD: list[tuple[str, dict[str, Any]]] = [
    ("rho_l_m", {"rho_l_m": -0.1}),
    ("rho_l_m", {"rho_l_m": float("nan")}),
    ("rho_u_m", {"rho_u_m": float("nan")}),
    ("rho_u_m", {"rho_l_m": 5.0}),
    ("rho_u_m", {"rho_u_m": 0.4}),
    ("rho_u_m", {"rho_u_m": -1.0}),
    ("n_bacteria", {"n_bacteria": 2}),
    ("n_bacteria", {"n_bacteria": 3, "dim": 3}),
    ("n_bacteria", {"n_bacteria": 60.0}),
    ("step_m", {"step_m": 0.0}),
    ("step_m", {"step_m": -0.4}),
    ("step_m", {"step_m": float("inf")}),
    ("mu_max", {"mu_min": 5, "mu_max": 4}),
    ("mu_min", {"mu_min": 0}),
    ("dim", {"dim": 4}),
    ("dim", {"dim": 1}),
    ("alpha_t", {"alpha_t": float("nan")}),
    ("alpha_t", {"alpha_t": 0.0}),
    ("alpha_o", {"alpha_o": -1.0}),
    ("mu_t_per_m2", {"mu_t_per_m2": 0.0}),
    ("mu_o_per_m2", {"mu_o_per_m2": float("inf")}),
    ("capf_k_att", {"capf_k_att": -1.0}),
    ("capf_eta", {"capf_eta": -1.0}),
    ("capf_rho_0_m", {"capf_rho_0_m": 0.0}),
    ("abapf_rule", {"abapf_rule": "exact"}),
    ("abapf_search", {"abapf_search": "grid"}),
    ("random_walk", {"random_walk": None}),
    ("agent_repulsion", {"agent_repulsion": 1}),
    ("nav_area_ne_m", {"nav_area_ne_m": (0.0, 0.0, 1.0, 1.0)}),  # under 8 cells a side
    ("nav_area_ne_m", {"nav_area_ne_m": (10.0, 0.0, 0.0, 10.0)}),  # min > max
    ("nav_area_ne_m", {"nav_area_ne_m": (0.0, 0.0, 10.0)}),
    ("nav_area_ne_m", {"nav_area_ne_m": (0.0, 0.0, float("nan"), 10.0)}),
    ("nav_area_ne_m", {"nav_area_ne_m": "0,0,10,10"}),
    ("nav_area_ne_m", {"nav_area_ne_m": ((0.0, 0.0), (10.0, 10.0))}),  # two pairs: a world file's corners, not here
    ("nav_area_ne_m", {"nav_area_ne_m": ((0.0, 0.0), (10.0, 10.0), (10.0, 0.0), (0.0, 12.0))}),  # edges cross
    ("nav_area_ne_m", {"nav_area_ne_m": ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0, 1.0))}),  # not a pair
    ("nav_area_ne_m", {"nav_area_ne_m": ((0.0, 0.0), (10.0, 0.0), (10.0, float("inf")))}),
    ("nav_area_ne_m", {"nav_area_ne_m": ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0))}),  # bounds under 8 cells a side
    (
        "nav_area_ne_m",
        {
            "nav_area_ne_m": tuple(
                (10.0 * math.cos(k * math.tau / 65), 10.0 * math.sin(k * math.tau / 65)) for k in range(65)
            )
        },
    ),
    ("nav_area_ne_m", {"nav_area_ne_m": ()}),
    ("nav_keepout_ne_m", {"nav_keepout_ne_m": (((0.0, 0.0), (1.0, 0.0)),)}),  # two vertices
    ("nav_keepout_ne_m", {"nav_keepout_ne_m": (((0.0, 0.0), (5.0, 5.0), (5.0, 0.0), (0.0, 6.0)),)}),  # edges cross
    ("nav_keepout_ne_m", {"nav_keepout_ne_m": ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0))}),  # a polygon, not a list of them
    ("nav_keepout_ne_m", {"nav_keepout_ne_m": (((0.0, 0.0), (1.0, 0.0), (1.0, math.nan)),)}),
    ("nav_keepout_ne_m", {"nav_keepout_ne_m": "0,0,1,0,1,1"}),
    ("nav_keepout_ne_m", {"nav_keepout_ne_m": tuple(((k, 0.0), (k + 1.0, 0.0), (k, 1.0)) for k in range(17))}),
]


def test_a_flying_area_is_kept_as_a_tuple_of_floats() -> None:
    assert PlannerParams().nav_area_ne_m is None
    p = PlannerParams(nav_area_ne_m=[-3, -12, 23, 12])  # type: ignore[arg-type]  # a config file gives a list
    assert p.nav_area_ne_m == (-3.0, -12.0, 23.0, 12.0)
    assert all(type(v) is float for v in p.nav_area_ne_m)
    assert PlannerParams(nav_area_ne_m=(0.0, 0.0, 76.8, 76.8)).nav_area_ne_m is not None  # 256 cells a side
    assert PlannerParams(nav_area_ne_m=(0.0, 0.0, 100.0, 10.0), nav_cell_m=0.4).nav_area_ne_m is not None
    # Wider than 256 cells: planned on the moving grid (``NavGrid``), no longer a config error.
    assert PlannerParams(nav_area_ne_m=(0.0, 0.0, 76.9, 10.0)).nav_area_ne_m is not None
    assert PlannerParams(nav_area_ne_m=((0.0, 0.0), (600.0, 0.0), (600.0, 10.0))).nav_area_ne_m is not None


def test_keep_out_zones_are_kept_as_tuples_of_float_pairs() -> None:
    """A config file gives ``[[[north, east], ...], ...]``: up to 16 polygons, kept in order as pairs of floats."""
    assert PlannerParams().nav_keepout_ne_m == ()
    p = PlannerParams(nav_keepout_ne_m=[[[0, 0], [2, 0], [2, 2]], [[5, 5], [6, 5], [6, 6], [5, 6]]])  # type: ignore[arg-type]
    assert p.nav_keepout_ne_m == (
        ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0)),
        ((5.0, 5.0), (6.0, 5.0), (6.0, 6.0), (5.0, 6.0)),
    )
    assert all(type(v) is float for zone in p.nav_keepout_ne_m for pair in zone for v in pair)
    sixteen = tuple(((k, 0.0), (k + 1.0, 0.0), (k, 1.0)) for k in range(16))
    assert len(PlannerParams(nav_keepout_ne_m=sixteen).nav_keepout_ne_m) == 16


def test_a_polygonal_area_is_kept_as_a_tuple_of_float_pairs() -> None:
    """A config file gives ``[[north, east], ...]``: kept in order as pairs of floats, up to 64 vertices."""
    l_shape = [[0, 0], [20, 0], [20, 8], [8, 8], [8, 20], [0, 20]]
    p = PlannerParams(nav_area_ne_m=l_shape)  # type: ignore[arg-type]
    assert p.nav_area_ne_m == ((0.0, 0.0), (20.0, 0.0), (20.0, 8.0), (8.0, 8.0), (8.0, 20.0), (0.0, 20.0))
    assert all(type(v) is float for pair in p.nav_area_ne_m for v in pair)
    circle = tuple((10.0 * math.cos(k * math.tau / 64), 10.0 * math.sin(k * math.tau / 64)) for k in range(64))
    assert PlannerParams(nav_area_ne_m=circle).nav_area_ne_m == circle


@pytest.mark.parametrize(("field", "kwargs"), BAD, ids=[f"{f}-{k}" for f, k in BAD])
def test_invalid_values_name_the_field(field: str, kwargs: dict[str, Any]) -> None:
    with pytest.raises(ConfigError, match=rf"PlannerParams\.{field} .*allowed"):
        PlannerParams(**kwargs)


def test_config_error_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="step_m"):
        dataclasses.replace(PlannerParams(), step_m=-1.0)


def test_rho_l_zero_is_allowed() -> None:
    assert PlannerParams(rho_l_m=0.0).rho_l_m == 0.0


def test_unknown_planner_lists_the_names() -> None:
    with pytest.raises(ConfigError, match="capf, bapf, a-bapf, cr-bapf, cr-bapf\\*"):
        get_planner("dwa")


@pytest.mark.parametrize("name", PLANNER_NAMES)
def test_every_name_builds(name: str) -> None:
    planner = get_planner(name, PlannerParams(dim=3, n_bacteria=30))
    assert planner.name == name
    assert planner.bacteria_offsets_m.shape == (30, 3)
