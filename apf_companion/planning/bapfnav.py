"""bapf-nav: the product planner. Bacteria points with real clearance, a swept move test and escape with memory.

Each step tests the N_b bacteria points around the agent (the paper's candidates, ``geometry.bacteria_offsets``):

1. Clearance. The straight move to a point is swept against every known obstacle point near the agent
   (``clearance.segment_clearance_sq``): no move ends or passes closer than C = vehicle radius + safety margin
   + noise_k * noise_std (``PlannerParams.clearance_m``). This is Eq. (13)'s +inf inside rho_l with rho_l = C,
   applied along the whole move instead of at its end. An agent already inside C (noise pushed it there) may
   only move so that it gets no closer along the way and ends farther out. Boxed in (no move keeps C, e.g. a
   pocket between obstacles 0.6-0.8 m away), it squeezes out along the move that keeps the most clearance,
   provided that is at least vehicle radius + safety margin: the noise margin is the only part ever spent.
2. Score. J_k = g(r_b,k) + sum_n a exp(-mu_c rho_o^n(r_b,k)) (+ a look-ahead penalty): the target term of
   Eq. (1) ranks points by their distance to the goal g (exp is monotone, so the ranking by -log|J_t| = mu_t g^2
   is the ranking by g; using g itself keeps the terms in metres), the clearance term has the form of Eq. (2)
   (``potentials.obstacle_potential``) at product scale. A point passes when J_k < J_a, Eq. (6); the best
   passing point is taken, not the first (the paper's first-passing rule grazes obstacles).
3. Escape with memory. In DIRECT mode g is the straight-line distance. The agent switches to ESCAPE, where g is
   the geodesic distance to the goal on a grid of the obstacles it has seen, inflated by C
   (``navfield.NavGrid``, no local minimum in front of a concave obstacle), as soon as a remembered surface
   blocks the straight line within ``nav_sight_m``, or any remembered point does within ``nav_sight_points_m``
   (``navsight.LineOfSight``), and in any case when no
   point passes (a local minimum of the paper's field). It leaves ESCAPE once the line is clear and it is closer
   to the goal than where the escape began (Bug2's leave rule), so it cannot fall back into the same trap. The
   potential is recomputed when the descent stalls, when a newly seen obstacle lies near its shortest way,
   and every ``nav_replan_steps`` steps (``navescape``); blocked cells are remembered across recomputations.
4. Stability. A turn of more than ``nav_hold_angle_deg`` from the previous move is taken only when it gains
   ``nav_hold_ratio`` times what the best point within that angle gains (BendyRuler's OA_BR_CONT_ANGLE /
   OA_BR_CONT_RATIO rule, applied to the score). In DIRECT mode each point also looks ahead: a probe of
   ``nav_lookahead_m`` from the point towards the goal that comes closer than C costs
   ``nav_lookahead_penalty_m``, so the side with an open view of the goal wins early.
5. Give-up. No path on the remembered map, or no new closest approach to the goal for ``nav_patience_steps``
   steps: ``DecisionReason.GAVE_UP`` (the caller reports STUCK), and no moves until the target changes.

Moves are reported as GREEDY (a passing point on the planner's potential); ``NavState.mode`` says which
potential. ``step`` (one agent, the service) runs the sight, trail and progress rules with ``navsingle.SingleStart``,
decides DIRECT steps with ``navone.DirectStep`` and ESCAPE steps (and a step that enters ESCAPE) with
``navescapeone.EscapeStep``: the same decisions and state in fewer numpy calls. 3D: the candidates
and the sweep are 3D; the escape potential is the horizontal geodesic distance combined with the vertical offset,
sqrt(g_h^2 + dz^2), from the obstacles within C of the agent's altitude.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.planning.area import outside_zones
from apf_companion.planning.decision import BatchDecision, Decision, DecisionReason
from apf_companion.planning.navescape import AgentRows, EscapeMaps
from apf_companion.planning.navescapeone import EscapeStep
from apf_companion.planning.navgeometry import MoveGeometry, obstacle_reach_m
from apf_companion.planning.navone import DirectStep
from apf_companion.planning.navsight import LineOfSight
from apf_companion.planning.navsingle import FIELD_AGE_CAP, SightLine, SingleStart, age_field
from apf_companion.planning.navstate import GiveUp, NavMode, NavState
from apf_companion.planning.params import PlannerParams
from apf_companion.planning.stateful import AgentState, StatefulPlanner, decision_from_choice

__all__ = ["BapfNavPlanner"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]

#: A new closest approach must beat the old one by this share of a step (noise-level jitter is no progress, and
#: an agent circling an enclosed goal cannot reset its patience for ever by creeping a millimetre closer).
_PROGRESS_SHARE = 0.25
#: Ages of fields stop counting here (``navsingle.FIELD_AGE_CAP``).
_AGE_CAP = np.int32(FIELD_AGE_CAP)
#: Spacing of the trail of visited positions (``NavState.record``; used by ``EscapeMaps.refresh``) [m].
_TRAIL_SPACING_M = 1.0
# NavMode codes as int8 scalars: comparing an array with an IntEnum member costs enum machinery on every call.
_DIRECT = np.int8(NavMode.DIRECT)
_ESCAPE = np.int8(NavMode.ESCAPE)
_GAVE_UP = np.int8(NavMode.GAVE_UP)
_GREEDY_CODE = np.int8(DecisionReason.GREEDY)
_LOCAL_MINIMUM_CODE = np.int8(DecisionReason.LOCAL_MINIMUM)
_GAVE_UP_CODE = np.int8(DecisionReason.GAVE_UP)
# The reductions behind ndarray.any / all / sum, called directly: the methods add a Python frame each, which at
# one agent is a noticeable share of a step (same ufunc reductions, same values).
_any = np.logical_or.reduce
_all = np.logical_and.reduce
_sum = np.add.reduce


def _age_fields(state: NavState) -> None:
    """A field kept from an earlier escape ages in DIRECT too (``_progress``); capped: no int32 overflow."""
    np.add(state.since_field, 1, out=state.since_field, where=state.since_field < _AGE_CAP)


class BapfNavPlanner(StatefulPlanner):
    """bapf-nav (module docstring)."""

    name = "bapf-nav"

    def __init__(self, params: PlannerParams) -> None:
        super().__init__(params)
        p = params
        self.clearance_m = p.clearance_m
        self._floor2 = (p.vehicle_radius_m + p.safety_margin_m) ** 2
        offsets = self.bacteria_offsets_m
        self._units = offsets / p.step_m
        self._geometry = MoveGeometry(p, offsets)
        self._escape = EscapeMaps(p, offsets, self.clearance_m)
        self._cos_hold = math.cos(math.radians(p.nav_hold_angle_deg))
        self._direct_one = DirectStep(p, offsets, self._units, self.clearance_m, obstacle_reach_m(p))
        self._escape_one = EscapeStep(self._escape, self._direct_one, offsets, self._units)
        self._sight = LineOfSight(p, self.clearance_m)
        sight = SightLine(p, self.clearance_m)
        self._start_one = SingleStart(p, self._sight, sight, _TRAIL_SPACING_M, _PROGRESS_SHARE)

    def initial_state(self, n_agents: int) -> NavState:
        return NavState.empty(n_agents, self.params.dim)

    def give_up_cause(self) -> GiveUp:
        """Why the single agent of ``step`` gave up (``GiveUp.NONE`` while it has not)."""
        state = self.own_state
        if not isinstance(state, NavState) or state.mode[0] != _GAVE_UP:
            return GiveUp.NONE
        return GiveUp(int(state.gave_up[0]))

    def _plan(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: AgentState,
    ) -> BatchDecision:
        assert isinstance(state, NavState)
        same = _all(state.target_m == targets_m, axis=1)
        if not _all(same, axis=None):
            changed = ~same
            self._restart(np.flatnonzero(changed), targets_m[changed], state)
        goal_vec, g0 = self._start(positions_m, targets_m, obstacles_m, obstacle_mask, state)
        return self._decide(positions_m, targets_m, obstacles_m, obstacle_mask, state, goal_vec, g0)

    def _start(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: NavState,
    ) -> tuple[FloatArray, FloatArray]:
        """Target minus position (A, D) and its length g0 (A,), after the sight, trail and progress rules."""
        goal_vec = targets_m - positions_m
        g0 = np.sqrt(np.einsum("ad,ad->a", goal_vec, goal_vec))
        # The line of sight decides entries (DIRECT agents) and exits (escaping agents past Bug2's leave point).
        looking = (state.mode == _DIRECT) | ((state.mode == _ESCAPE) & (g0 < state.hit_dist_m - self.params.step_m))
        blocked = self._sight.blocked(looking, positions_m, targets_m, obstacles_m, obstacle_mask)
        state.record(positions_m, _TRAIL_SPACING_M)
        self._progress(state, g0, blocked)
        return goal_vec, g0

    def step(
        self,
        position_m: npt.ArrayLike,
        target_m: npt.ArrayLike,
        obstacles_m: npt.ArrayLike,
        rng: np.random.Generator | None = None,
    ) -> Decision:
        """``StatefulPlanner.step``; the single-agent path (``navsingle``, then ``navone`` for a DIRECT step and
        ``navescapeone`` for an ESCAPE step), the same decision. A GAVE_UP agent or non-finite numbers: the batch
        path."""
        pos, tgt, obs, state = self._one(position_m, target_m, obstacles_m)
        assert isinstance(state, NavState)
        if state.target_m[0].tolist() != tgt.tolist():  # also NaN (no target yet): NaN != NaN
            self._restart(np.zeros(1, dtype=np.intp), tgt[None], state)
        goal_vec, g0, rel, r2 = self._start_one(pos, tgt, obs, state)
        mode = state.mode[0]
        if mode == _GAVE_UP or not math.isfinite(g0):  # (finite g0: finite position and target) the batch path
            return self._decide(pos[None], tgt[None], obs[None], None, state, goal_vec[None], np.array([g0])).row(0)
        if mode == _ESCAPE:
            return self._escape_one(pos, tgt, obs, rel, r2, state)
        decision = self._direct_one(pos, rel, r2, goal_vec, g0, state.prev_dir)
        if decision is None:  # no point passes: the agent enters ESCAPE (``_escaping``)
            state.mode[0], state.hit_dist_m[0], state.field[0] = _ESCAPE, g0, None
            return self._escape_one(pos, tgt, obs, rel, r2, state, self._direct_one.trapped)
        if decision.chosen_index is not None:
            state.prev_dir[0] = self._units[decision.chosen_index]
        age_field(state)
        return decision

    def _restart(self, rows: npt.NDArray[np.intp], targets_m: FloatArray, state: NavState) -> None:
        """A new target for ``rows``: forget the old one; a target outside the flying area (``nav_area_ne_m``) or in
        a keep-out zone has no way, so the agent gives up at once instead of flying out of the area."""
        state.restart(rows, targets_m)
        outside = self.outside_area(targets_m[:, 0], targets_m[:, 1])
        state.mode[rows[outside]] = _GAVE_UP
        state.gave_up[rows[outside]] = GiveUp.OUTSIDE_AREA

    def outside_area(self, north_m: npt.ArrayLike, east_m: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Whether each finite point lies outside the flying area (``nav_area_ne_m``) or in a keep-out zone
        (``nav_keepout_ne_m``): a target there has no way (the service refuses such goals)."""
        north, east = np.asarray(north_m, dtype=np.float64), np.asarray(east_m, dtype=np.float64)
        out = outside_zones(self.params.nav_area_ne_m, self.params.nav_keepout_ne_m, north, east)
        finite: npt.NDArray[np.bool_] = np.isfinite(north) & np.isfinite(east)
        return out & finite

    def _decide(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: NavState,
        goal_vec: FloatArray,
        g0: FloatArray,
    ) -> BatchDecision:
        """The step after the target and progress rules (``_plan``): scores, escape, choice."""
        offsets = self.bacteria_offsets_m
        to_goal = goal_vec[:, None, :] - offsets[None, :, :]
        g_k = np.sqrt(np.einsum("akd,akd->ak", to_goal, to_goal))
        direct = state.mode == _DIRECT
        feasible, seg2, clear_k, clear_0, look_k = self._geometry(
            positions_m, obstacles_m, obstacle_mask, to_goal, g_k, direct
        )
        cost = g_k + clear_k + look_k
        cost0 = g0 + clear_0
        active = state.mode != _GAVE_UP
        passing = feasible & (cost < cost0[:, None]) & active[:, None]

        any_feasible: BoolArray = _any(feasible, axis=1)
        escaping = self._escaping(state, direct, passing, any_feasible, g0)
        some_escape = bool(_any(escaping, axis=None))
        if some_escape:
            world = AgentRows(positions_m, targets_m, obstacles_m, obstacle_mask, state)
            self._escape.scores(np.flatnonzero(escaping), world, feasible, clear_k, clear_0, cost, cost0, passing)

        chosen = _choose(cost, cost0, passing, state.prev_dir, self._units, self._cos_hold, self.params.nav_hold_ratio)
        _squeeze_out(chosen, ~any_feasible & active, seg2, self._floor2)
        gave_up = state.mode == _GAVE_UP
        some_gave_up = bool(_any(gave_up, axis=None))
        if some_gave_up:
            chosen[gave_up] = -1
        moved = chosen >= 0
        reason = np.where(moved, _GREEDY_CODE, _LOCAL_MINIMUM_CODE)
        if some_gave_up:
            reason[gave_up] = _GAVE_UP_CODE
        state.prev_dir[moved] = self._units[chosen[moved]]
        _age_fields(state)
        scores = np.where(passing, cost, np.inf)  # what the viz colours the candidates by
        return decision_from_choice(
            positions_m, offsets, chosen, reason, _sum(passing, axis=1), _sum(feasible, axis=1), candidate_cost=scores
        )

    @staticmethod
    def _escaping(
        state: NavState, direct: BoolArray, passing: BoolArray, any_feasible: BoolArray, g0: FloatArray
    ) -> BoolArray:
        """(A,) agents that plan on the escape potential: those already escaping, and those whose direct step
        found no passing point (they enter ESCAPE here, remembering where: Bug2's leave rule). ``direct``: the
        agents in DIRECT mode; ``any_feasible``: the agents with a feasible move."""
        escaping = state.mode == _ESCAPE
        trapped = direct & ~_any(passing, axis=1) & any_feasible
        if _any(trapped, axis=None):
            rows = np.flatnonzero(trapped)
            state.mode[rows] = _ESCAPE
            state.hit_dist_m[rows] = g0[rows]
            state.field[rows] = None
            escaping = escaping | trapped
        return np.asarray(escaping)

    def _progress(self, state: NavState, g0: FloatArray, blocked: BoolArray) -> None:
        """Closest approach, the modes' switches by sight and by the escape's leave rule, give-up by patience.

        ``blocked``: the agents whose straight line to the goal crosses the remembered map (``nav_sight_m``).
        A DIRECT agent whose line is blocked enters ESCAPE now, before a concave obstacle can trap it; it keeps
        a field from an earlier escape (``EscapeMaps.potentials`` recomputes it when it is ``nav_replan_steps``
        old). An escaping agent leaves once its line is clear and it is closer to the goal than where the
        escape began, less one step (Bug2's leave rule), so it cannot fall back into the same trap.
        """
        improved = g0 < state.best_dist_m - _PROGRESS_SHARE * self.params.step_m
        np.copyto(state.best_dist_m, g0, where=improved)
        state.since_best += 1
        state.since_best[improved] = 0
        escaping = state.mode == _ESCAPE
        if _any(escaping, axis=None):
            leave = escaping & (g0 < state.hit_dist_m - self.params.step_m) & ~blocked
            state.mode[leave] = _DIRECT
        sighted = (state.mode == _DIRECT) & blocked
        if _any(sighted, axis=None):
            state.mode[sighted] = _ESCAPE
            state.hit_dist_m[sighted] = g0[sighted]
        tired = state.since_best > self.params.nav_patience_steps
        if _any(tired, axis=None):
            state.gave_up[tired & (state.mode != _GAVE_UP)] = GiveUp.NO_PROGRESS
            state.mode[tired] = _GAVE_UP


def _squeeze_out(chosen: IntArray, boxed: BoolArray, seg2: FloatArray, floor2: float) -> None:
    """Boxed in: no move keeps the full clearance C (the noise margin is spent, e.g. noise pushed the agent into
    a pocket). Squeeze out along the move that keeps the most, if that still keeps radius + safety margin
    (``floor2``, squared); never closer. Without this the agent would sit there until its patience ran out."""
    if _any(boxed, axis=None):
        rows = np.flatnonzero(boxed)
        room = np.where(seg2[rows] >= floor2, seg2[rows], -np.inf)
        widest = np.argmax(room, axis=1)
        chosen[rows] = np.where(np.isfinite(room[np.arange(rows.size), widest]), widest, -1)


def _choose(
    cost: FloatArray,
    cost0: FloatArray,
    passing: BoolArray,
    prev_dir: FloatArray,
    units: FloatArray,
    cos_hold: float,
    hold_ratio: float,
) -> IntArray:
    """Best passing point, with the turn hysteresis (``nav_hold_angle_deg``, ``nav_hold_ratio``); -1 where none
    passes. ``units``: the bacteria offsets as unit vectors."""
    masked = np.where(passing, cost, np.inf)
    best = masked.argmin(axis=1)
    any_pass = _any(passing, axis=1)
    cos_turn = np.einsum("ad,kd->ak", prev_dir, units)  # (A, K); 0 without a previous move
    has_prev = _any(prev_dir != 0.0, axis=1)
    rows = np.arange(cost.shape[0])
    sharp = has_prev & any_pass & (cos_turn[rows, best] < cos_hold)
    if _any(sharp, axis=None):
        held = np.where(passing & (cos_turn >= cos_hold), cost, np.inf)
        alt = held.argmin(axis=1)
        alt_ok = np.isfinite(held[rows, alt])
        with np.errstate(invalid="ignore"):  # inf - inf where the fallback left cost0 = inf: no hold
            gain_best = cost0 - masked[rows, best]
            gain_alt = cost0 - held[rows, alt]
        keep = sharp & alt_ok & (gain_best < hold_ratio * gain_alt)
        best = np.where(keep, alt, best)
    return np.where(any_pass, best, -1).astype(np.intp)
