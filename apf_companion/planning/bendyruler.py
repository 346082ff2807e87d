"""bendyruler: a comparison baseline after ArduPilot's published description of its OA BendyRuler.

Written from the ArduPilot wiki ("Object Avoidance with Bendy Ruler", common-oa-bendyruler.rst) and the OA_*
parameter descriptions only (the ArduPilot source is GPL; this project is MIT, so no code was consulted or
copied). What those documents say:

- "The BendyRuler algorithm probes around the vehicle in many directions looking for open spaces and then tries
  to pick the direction that is sufficiently open while also moving the vehicle towards the final destination."
- OA_BR_LOOKAHEAD: the distance ahead of the vehicle that is probed; obstacles farther away are ignored.
- OA_MARGIN_MAX: the distance the vehicle should stay away from obstacles.
- OA_BR_CONT_RATIO: BendyRuler avoids changing bearing unless the ratio of the previous margin from obstacles
  to the present calculated margin is at least this much.
- OA_BR_CONT_ANGLE: BendyRuler resists changing the current bearing if the change is over this angle.

This project's reading, with the bacteria directions as the probes (the same sensing and step as the other rows):
a probe along bearing k is a "ruler" of ``br_lookahead_m`` from the agent, followed at its end by a second ruler
of the same length, bent towards the goal or straight on, whichever is more open (hence "bendy"); its margin is
the smallest distance from an obstacle to the first ruler and the chosen second one. Probes are tried in order of
increasing angle from the goal bearing; the first whose margin is at least ``br_margin_max_m`` is sufficiently
open. If none is, the probe with the largest margin is taken, and then a change of bearing by more than
``br_cont_angle_deg`` from the previous move is made only when the new margin is at least ``br_cont_ratio`` times
the previous bearing's margin (or the previous bearing is no longer safe): without that restriction to the
no-open-probe case, a previous bearing away from the goal would be kept for ever. The agent then moves
``step_m`` along the chosen bearing, provided that step keeps vehicle radius + safety margin; otherwise it does
not move (LOCAL_MINIMUM). It has no memory beyond the last bearing and no give-up rule.

It is a comparison row for the study, not a port of ArduPilot and not flown by default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Self

import numpy as np
import numpy.typing as npt

from apf_companion.planning.clearance import near_obstacles, segment_clearance_sq, segments_clearance_sq
from apf_companion.planning.decision import BatchDecision, DecisionReason
from apf_companion.planning.params import PlannerParams
from apf_companion.planning.stateful import AgentState, StatefulPlanner, decision_from_choice

__all__ = ["BendyRulerPlanner", "BendyRulerState"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Agents per group of the probe geometry.
_GROUP = 16


@dataclass(slots=True)
class BendyRulerState:
    """Rows of agents: the target and the unit direction of the last move (zeros: none)."""

    target_m: FloatArray
    prev_dir: FloatArray

    def __len__(self) -> int:
        return int(self.target_m.shape[0])

    def take(self, rows: npt.NDArray[np.intp] | BoolArray) -> Self:
        return type(self)(**{f.name: getattr(self, f.name)[rows].copy() for f in fields(self)})

    def put(self, rows: npt.NDArray[np.intp], other: Self) -> None:
        for f in fields(self):
            getattr(self, f.name)[rows] = getattr(other, f.name)


class BendyRulerPlanner(StatefulPlanner):
    """The BendyRuler-style baseline (module docstring)."""

    name = "bendyruler"

    def __init__(self, params: PlannerParams) -> None:
        super().__init__(params)
        self._units = self.bacteria_offsets_m / params.step_m
        self._cos_cont = math.cos(math.radians(params.br_cont_angle_deg))
        self._floor_m = params.vehicle_radius_m + params.safety_margin_m

    def initial_state(self, n_agents: int) -> BendyRulerState:
        dim = self.params.dim
        return BendyRulerState(target_m=np.full((n_agents, dim), np.nan), prev_dir=np.zeros((n_agents, dim)))

    def _plan(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: AgentState,
    ) -> BatchDecision:
        assert isinstance(state, BendyRulerState)
        p = self.params
        n_agents = positions_m.shape[0]
        changed = ~np.all(state.target_m == targets_m, axis=1)
        state.target_m[changed] = targets_m[changed]
        state.prev_dir[changed] = 0.0
        goal_vec = targets_m - positions_m
        g0 = np.sqrt(np.einsum("ad,ad->a", goal_vec, goal_vec))
        margin = np.empty((n_agents, self._units.shape[0]))
        safe = np.empty(margin.shape, dtype=bool)
        for lo in range(0, n_agents, _GROUP):  # small work arrays (see bapfnav._geometry)
            g = slice(lo, min(lo + _GROUP, n_agents))
            mask = None if obstacle_mask is None else obstacle_mask[g]
            margin[g], safe[g] = self._probe(positions_m[g], obstacles_m[g], mask, goal_vec[g], g0[g])

        # Probe order: increasing angle from the goal bearing (ties: lower index).
        with np.errstate(invalid="ignore", divide="ignore"):
            goal_unit = np.where(g0[:, None] > 0.0, goal_vec / g0[:, None], 0.0)
        cos_goal = np.einsum("ad,kd->ak", goal_unit, self._units)  # not @: BLAS rounding differs with A
        open_ = safe & (margin >= p.br_margin_max_m)
        first_open = np.argmax(np.where(open_, cos_goal, -np.inf), axis=1)
        widest = np.argmax(np.where(safe, margin, -np.inf), axis=1)
        rows = np.arange(n_agents)
        chosen = np.where(open_.any(axis=1), first_open, widest)
        widest_only = ~open_.any(axis=1)
        chosen = np.where(widest_only, self._continuity(chosen, margin, safe, state.prev_dir), chosen)
        ok = safe[rows, chosen]
        chosen = np.where(ok, chosen, -1)
        moved = chosen >= 0
        state.prev_dir[moved] = self._units[chosen[moved]]
        reason = np.where(moved, DecisionReason.GREEDY, DecisionReason.LOCAL_MINIMUM).astype(np.int8)
        offsets = self.bacteria_offsets_m
        return decision_from_choice(positions_m, offsets, chosen, reason, open_.sum(axis=1), safe.sum(axis=1))

    def _probe(
        self,
        positions_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        goal_vec: FloatArray,
        g0: FloatArray,
    ) -> tuple[FloatArray, BoolArray]:
        """Margins of the bent rulers (A, K) [m] and which first steps keep radius + safety margin (A, K)."""
        p = self.params
        look = p.br_lookahead_m
        rel, valid = near_obstacles(positions_m, obstacles_m, obstacle_mask, 2.0 * look + p.br_margin_max_m)
        # Ruler 1: along each bearing (no longer than the way to the goal); ruler 2: from its end to the goal.
        len1 = np.clip(g0, p.step_m, look)
        ruler1 = self._units[None, :, :] * len1[:, None, None]
        to_goal = goal_vec[:, None, :] - ruler1
        dist2 = np.sqrt(np.einsum("akd,akd->ak", to_goal, to_goal))
        with np.errstate(invalid="ignore", divide="ignore"):
            ruler2 = np.where(dist2[..., None] > 0.0, to_goal * (np.minimum(dist2, look) / dist2)[..., None], 0.0)
        zeros = np.zeros_like(ruler1)
        m1 = segments_clearance_sq(rel, valid, zeros, ruler1)
        # The bend: from the end of ruler 1 towards the goal, or straight on; the more open of the two counts.
        m2 = np.maximum(
            segments_clearance_sq(rel, valid, ruler1, ruler2), segments_clearance_sq(rel, valid, ruler1, ruler1)
        )
        margin = np.sqrt(np.minimum(m1, m2))
        step2 = segment_clearance_sq(rel, valid, self.bacteria_offsets_m)
        return margin, np.sqrt(step2) >= self._floor_m

    def _continuity(
        self, chosen: npt.NDArray[np.intp], margin: FloatArray, safe: BoolArray, prev_dir: FloatArray
    ) -> npt.NDArray[np.intp]:
        """OA_BR_CONT_ANGLE / OA_BR_CONT_RATIO: keep the previous bearing unless the new one is clearly better."""
        has_prev = np.any(prev_dir != 0.0, axis=1)
        if not has_prev.any():
            return chosen
        rows = np.arange(chosen.shape[0])
        cos_prev = np.einsum("ad,kd->ak", prev_dir, self._units)
        prev_k = np.argmax(cos_prev, axis=1)  # the probe closest to the previous bearing
        turn = cos_prev[rows, chosen] < self._cos_cont
        prev_ok = safe[rows, prev_k]
        better = margin[rows, chosen] >= self.params.br_cont_ratio * margin[rows, prev_k]
        keep = has_prev & turn & prev_ok & ~better
        return np.where(keep, prev_k, chosen)
