"""apf_companion.planning: the pure planning core (numpy only; no clocks, I/O or global state).

Planners of Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered
Environments", IEEE Aerospace 2023 (DOI 10.1109/AERO55745.2023.10115857): CAPF, BAPF, A-BAPF, CR-BAPF and
CR-BAPF*, in 2D and 3D, batch-first::

    planner = get_planner("cr-bapf*", PlannerParams())
    decision = planner.step(position_m, target_m, obstacles_m, rng)
    batch = planner.step_batch(positions_m, targets_m, obstacles_m, obstacle_mask, rng)

and the product planner ``bapf-nav`` (``bapfnav.py``, stateful: ``stateful.py``) with the ``bendyruler``
comparison baseline (``bendyruler.py``).
"""

from __future__ import annotations

from apf_companion.planning.abapf import AbapfPlanner
from apf_companion.planning.area import (
    AreaNE,
    FlyingArea,
    KeepOuts,
    PolygonNE,
    ZoneConflict,
    area_bounds,
    area_polygon,
    area_text,
    in_keepout,
    inside_area,
    is_polygon,
    polygon_problem,
    zone_conflict,
)
from apf_companion.planning.bapf import BapfPlanner
from apf_companion.planning.bapfnav import BapfNavPlanner
from apf_companion.planning.base import Planner
from apf_companion.planning.bendyruler import BendyRulerPlanner, BendyRulerState
from apf_companion.planning.capf import CapfPlanner
from apf_companion.planning.crbapf import CrBapfPlanner, CrBapfStarPlanner
from apf_companion.planning.decision import BatchDecision, Decision, DecisionReason
from apf_companion.planning.geometry import bacteria_offsets, bacteria_ring, bacteria_sphere
from apf_companion.planning.navstate import GiveUp, NavMode, NavState
from apf_companion.planning.params import AbapfRule, AbapfSearch, PlannerParams, Preset, RandomWalkRule
from apf_companion.planning.potentials import (
    agent_potential,
    branch_obstacle_potential,
    log_sum_exp,
    moves_downhill,
    obstacle_potential,
    target_potential,
    total_obstacle_potential,
)
from apf_companion.planning.registry import (
    ALL_PLANNER_NAMES,
    DEFAULT_PLANNER,
    PAPER_PLANNER_NAMES,
    PLANNER_NAMES,
    PlannerName,
    get_planner,
)
from apf_companion.planning.stateful import AgentState, StatefulPlanner

__all__ = [
    "ALL_PLANNER_NAMES",
    "DEFAULT_PLANNER",
    "PAPER_PLANNER_NAMES",
    "PLANNER_NAMES",
    "AbapfPlanner",
    "AbapfRule",
    "AbapfSearch",
    "AgentState",
    "AreaNE",
    "BapfNavPlanner",
    "BapfPlanner",
    "BatchDecision",
    "BendyRulerPlanner",
    "BendyRulerState",
    "CapfPlanner",
    "CrBapfPlanner",
    "CrBapfStarPlanner",
    "Decision",
    "DecisionReason",
    "FlyingArea",
    "GiveUp",
    "KeepOuts",
    "NavMode",
    "NavState",
    "Planner",
    "PlannerName",
    "PlannerParams",
    "PolygonNE",
    "Preset",
    "RandomWalkRule",
    "StatefulPlanner",
    "ZoneConflict",
    "agent_potential",
    "area_bounds",
    "area_polygon",
    "area_text",
    "bacteria_offsets",
    "bacteria_ring",
    "bacteria_sphere",
    "branch_obstacle_potential",
    "get_planner",
    "in_keepout",
    "inside_area",
    "is_polygon",
    "log_sum_exp",
    "moves_downhill",
    "obstacle_potential",
    "polygon_problem",
    "target_potential",
    "total_obstacle_potential",
    "zone_conflict",
]
