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
open, and probing stops there (the decision's ``n_passing`` counts the open probes it saw, ``n_safe`` every safe
first step). If none is, the probe with the largest margin is taken, and then a change of bearing by more than
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

from apf_companion.planning.clearance import compact_rows, segment_clearance_sq
from apf_companion.planning.decision import BatchDecision, DecisionReason
from apf_companion.planning.params import PlannerParams
from apf_companion.planning.stateful import AgentState, StatefulPlanner, decision_from_choice

__all__ = ["BendyRulerPlanner", "BendyRulerState"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Agents per group of the probe geometry (at least), and obstacles x agents x probes per group (small work
#: arrays: megabyte temporaries cost page faults on every call). Session 29, the study's bendyruler rows at 1000
#: trials under cProfile: 16 agents -> 2.44 s in ``_margins``, 32 -> 2.30, 64 -> 2.29 (10 000 elements: the same).
_GROUP = 32
_GROUP_ELEMENTS = 5_000
#: Probing stages: ranks [0, 3), [3, 10), [10, 30), then the rest. Most agents find an open probe in the first
#: stage or two (measured in the study at 70-95 obstacles: 37 % at rank 0, 54 % within 4 ranks, 84 % within 16,
#: 5.5 % never).
_STAGES = (3, 10, 30)
#: Agents x remaining probes below which all remaining probes are measured in one stage.
_FEW_PROBES = 2400
#: Stages of at most this many probes first drop the obstacles far from all of their probes (``_margins``).
_FOCUS_PROBES = 10
#: Extra reach of the obstacle prefilters of the step test [m] (it keeps every obstacle that can matter).
_SLACK_M = 0.01

_World = tuple[FloatArray, BoolArray, FloatArray, FloatArray]
"""(near obstacles relative to the agents, their mask, goal vectors, goal distances) of a step."""


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
        n_agents = positions_m.shape[0]
        changed = ~np.all(state.target_m == targets_m, axis=1)
        state.target_m[changed] = targets_m[changed]
        state.prev_dir[changed] = 0.0
        goal_vec = targets_m - positions_m
        g0 = np.sqrt(np.einsum("ad,ad->a", goal_vec, goal_vec))
        # Obstacles that can matter to any probe (their geometry lies within 2 br_lookahead_m of the agent).
        p = self.params
        rel, valid = _near(positions_m, obstacles_m, obstacle_mask, 2.0 * p.br_lookahead_m + p.br_margin_max_m)
        safe = self._safe(rel, valid)
        # Probe order: increasing angle from the goal bearing (ties: lower index).
        with np.errstate(invalid="ignore", divide="ignore"):
            goal_unit = np.where(g0[:, None] > 0.0, goal_vec / g0[:, None], 0.0)
        cos_goal = _cosines(goal_unit, self._units)
        order = np.argsort(-cos_goal, axis=1, kind="stable")
        world = (rel, valid, goal_vec, g0)
        margin, first_open, n_open = self._search(order, safe, world)
        rows = np.arange(n_agents)
        found = first_open >= 0
        # None open: the widest safe probe (every probe's margin is known for these agents), with continuity.
        widest = np.argmax(np.where(safe, margin, -np.inf), axis=1)
        chosen = np.where(found, first_open, self._continuity(widest, margin, safe, state.prev_dir))
        ok = safe[rows, chosen]
        chosen = np.where(ok, chosen, -1)
        moved = chosen >= 0
        state.prev_dir[moved] = self._units[chosen[moved]]
        reason = np.where(moved, DecisionReason.GREEDY, DecisionReason.LOCAL_MINIMUM).astype(np.int8)
        offsets = self.bacteria_offsets_m
        return decision_from_choice(positions_m, offsets, chosen, reason, n_open, safe.sum(axis=1))

    def _safe(self, rel: FloatArray, valid: BoolArray) -> BoolArray:
        """(A, K) first steps that keep radius + safety margin. Only obstacles within a step plus that floor can
        break it, so only those are swept (the same arithmetic per obstacle as over all of them)."""
        reach = self.params.step_m + self._floor_m + _SLACK_M
        near, near_valid = compact_rows(rel, valid & (_sq_norm(rel) <= reach * reach))
        step2 = segment_clearance_sq(near, near_valid, self.bacteria_offsets_m)
        return np.asarray(np.sqrt(step2) >= self._floor_m)

    def _search(
        self, order: npt.NDArray[np.intp], safe: BoolArray, world: _World
    ) -> tuple[FloatArray, npt.NDArray[np.intp], npt.NDArray[np.intp]]:
        """Probe in order of angle from the goal, in stages of ranks (``_STAGES``), until each agent has an open
        probe (safe and margin >= ``br_margin_max_m``): the first one is chosen, the rest are never probed.

        Returns margins (A, K) (NaN where not probed; complete for agents with no open probe), the first open
        probe (A,) (-1: none) and how many open probes each agent's probing saw (A,)."""
        n_agents, n_probes = order.shape
        margin = np.full((n_agents, n_probes), np.nan)
        first_open = np.full(n_agents, -1, dtype=np.intp)
        n_open = np.zeros(n_agents, dtype=np.intp)
        todo = np.arange(n_agents)
        lo = 0
        for stage_end in (*_STAGES, n_probes):
            if todo.size == 0 or lo >= n_probes:
                break
            # A few agents left (the long tail of a study chunk): all their remaining probes at once, the work is
            # small and each stage costs the same fixed numpy overhead.
            few = todo.size * (n_probes - lo) <= _FEW_PROBES
            hi = n_probes if few else min(stage_end, n_probes)
            k = order[todo, lo:hi]  # (R, S) probe indices by rank
            m = self._margins(todo, k, world)
            margin[todo[:, None], k] = m
            open_ = safe[todo[:, None], k] & (m >= self.params.br_margin_max_m)
            n_open[todo] += open_.sum(axis=1)
            hit = open_.any(axis=1)
            first_open[todo[hit]] = k[hit, np.argmax(open_[hit], axis=1)]
            todo = todo[~hit]
            lo = hi
        return margin, first_open, n_open

    def _margins(self, rows: npt.NDArray[np.intp], k: npt.NDArray[np.intp], world: _World) -> FloatArray:
        """Margins (R, S) of probes ``k`` (R, S) of agents ``rows``.

        A probe's three segments lie within ``br_lookahead_m`` of the end of its first ruler, so an obstacle
        farther than that plus ``br_margin_max_m`` from the ends of all the probes asked for cannot bring a margin
        below ``br_margin_max_m``: it is left out (a margin from there up is only ever compared with that
        threshold). The agents then go in groups of similar obstacle counts, each group's work arrays as wide as
        its own largest count and about ``_GROUP_ELEMENTS`` elements in all."""
        rel_all, valid_all, goal_vec, g0 = world
        p = self.params
        rel, valid = rel_all[rows], valid_all[rows]
        if k.shape[1] <= _FOCUS_PROBES and rel.shape[1] > 0:
            ends = self._units[k] * np.clip(g0[rows], p.step_m, p.br_lookahead_m)[:, None, None]  # (R, S, D)
            reach = p.br_lookahead_m + p.br_margin_max_m + _SLACK_M
            rel, valid = compact_rows(rel, valid & _near_any(rel, ends, reach))
        counts = valid.sum(axis=1)
        by_count = np.argsort(counts, kind="stable")
        out = np.empty(k.shape)
        lo = 0
        while lo < rows.size:
            width = max(int(counts[by_count[min(lo + _GROUP, rows.size) - 1]]), 1)
            hi = min(lo + max(_GROUP, _GROUP_ELEMENTS // (width * k.shape[1])), rows.size)
            g = by_count[lo:hi]
            width = int(counts[g[-1]])
            r = rows[g]
            out[g] = self._probe(rel[g, :width], valid[g, :width], goal_vec[r], g0[r], k[g])
            lo = hi
        return out

    def _probe(
        self, rel: FloatArray, valid: BoolArray, goal_vec: FloatArray, g0: FloatArray, k: npt.NDArray[np.intp]
    ) -> FloatArray:
        """Margins of the bent rulers along bearings ``k`` (A, S) [m], obstacles ``rel`` (A, M, D) relative to the
        agents (``near_obstacles``)."""
        p = self.params
        look = p.br_lookahead_m
        # Ruler 1: along each bearing (no longer than the way to the goal); ruler 2: from its end to the goal.
        len1 = np.clip(g0, p.step_m, look)
        ruler1 = self._units[k] * len1[:, None, None]
        to_goal = goal_vec[:, None, :] - ruler1
        dist2 = np.sqrt(_sq_norm(to_goal))
        with np.errstate(invalid="ignore", divide="ignore"):
            ruler2 = np.where(dist2[..., None] > 0.0, to_goal * (np.minimum(dist2, look) / dist2)[..., None], 0.0)
        m1, bent, straight = _rulers_sq(rel, valid, ruler1, ruler2)
        # The bend or straight on: the more open of the two counts.
        m2 = np.maximum(bent, straight)
        return np.asarray(np.sqrt(np.minimum(m1, m2)), dtype=np.float64)

    def _continuity(
        self, chosen: npt.NDArray[np.intp], margin: FloatArray, safe: BoolArray, prev_dir: FloatArray
    ) -> npt.NDArray[np.intp]:
        """OA_BR_CONT_ANGLE / OA_BR_CONT_RATIO: keep the previous bearing unless the new one is clearly better."""
        has_prev = np.any(prev_dir != 0.0, axis=1)
        if not has_prev.any():
            return chosen
        rows = np.arange(chosen.shape[0])
        cos_prev = _cosines(prev_dir, self._units)
        prev_k = np.argmax(cos_prev, axis=1)  # the probe closest to the previous bearing
        turn = cos_prev[rows, chosen] < self._cos_cont
        prev_ok = safe[rows, prev_k]
        better = margin[rows, chosen] >= self.params.br_cont_ratio * margin[rows, prev_k]
        keep = has_prev & turn & prev_ok & ~better
        return np.where(keep, prev_k, chosen)


def _rulers_sq(
    rel: FloatArray, valid: BoolArray, ruler1: FloatArray, ruler2: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(A, S) squared clearance of ruler 1 (0 -> ruler1), the bend (ruler1 -> ruler1 + ruler2) and the straight
    continuation (ruler1 -> 2 ruler1) to the valid obstacles ``rel`` (A, M, D) (inf without any).

    Element for element the arithmetic of ``clearance.segments_clearance_sq`` (the digests pin it), with what the
    three segments share computed once: ruler 1 starts at the agent, so its obstacle offsets are the obstacles
    themselves; both second rulers start at the end of ruler 1.

    Layout: every (M, A, S) operand is a whole contiguous array and every (A, S) one a contiguous plane, so each
    ufunc runs one inner loop over A S elements per obstacle. An (M, A, 1) operand broadcast against an (A, S)
    one has an inner loop of S (3 in the first stage), which numpy runs through buffered copies at about twice
    the cost; ``np.repeat`` makes the whole arrays once (elementwise IEEE operations: the same values)."""
    dim = rel.shape[2]
    n_probes = ruler1.shape[1]
    planes = [np.ascontiguousarray(rel[:, :, d].T)[:, :, None] for d in range(dim)]  # (M, A, 1) each
    r2_agent = planes[0] * planes[0]
    for d in range(1, dim):
        r2_agent += planes[d] * planes[d]
    # Padding rows (rel = 0) start from |rel|^2 = inf, which every segment's inf - finite keeps: the squared norms
    # are marked once instead of each segment's result.
    invalid = None if valid.all() else ~valid.T[:, :, None]
    if invalid is not None:
        np.copyto(r2_agent, np.inf, where=invalid)
    axes = [np.repeat(a, n_probes, axis=2) for a in planes]  # (M, A, S) each
    r2_agent = np.repeat(r2_agent, n_probes, axis=2)
    r1 = [np.ascontiguousarray(ruler1[:, :, d]) for d in range(dim)]  # (A, S) each
    r2 = [np.ascontiguousarray(ruler2[:, :, d]) for d in range(dim)]
    offsets = [axes[d] - r1[d] for d in range(dim)]  # (M, A, S): obstacle minus the end of ruler 1
    r2_end = offsets[0] * offsets[0]
    for d in range(1, dim):
        r2_end += offsets[d] * offsets[d]
    if invalid is not None:
        np.copyto(r2_end, np.inf, where=invalid)
    len1_sq = _sq_norm(ruler1)
    return (
        _segment_min_sq(axes, r2_agent, r1, len1_sq),
        _segment_min_sq(offsets, r2_end, r2, _sq_norm(ruler2)),
        _segment_min_sq(offsets, r2_end, r1, len1_sq),
    )


def _segment_min_sq(rel: list[FloatArray], r2: FloatArray, vectors: list[FloatArray], v2: FloatArray) -> FloatArray:
    """min over obstacles of |rel - t v|^2, t = clip(rel.v / |v|^2, 0, 1) (0 for a zero-length v), (A, S); ``rel``
    and ``r2`` (M, A, S), the coordinate planes of v (A, S) each and ``v2`` = |v|^2 (A, S). The clip at 0 after the
    minimum (monotone, so bit for bit the minimum of the clipped values; d2 is never NaN or -0.0)."""
    dot = rel[0] * vectors[0]
    for d in range(1, len(rel)):
        dot += rel[d] * vectors[d]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = dot / v2
    np.fmax(t, 0.0, out=t)  # also NaN from a zero-length vector: the segment is its start point
    np.minimum(t, 1.0, out=t)
    dot *= 2.0
    dot -= t * v2
    dot *= t
    np.subtract(r2, dot, out=dot)
    out = np.minimum.reduce(dot, axis=0, initial=np.inf)
    return np.asarray(np.maximum(out, 0.0, out=out), dtype=np.float64)


def _near_any(rel: FloatArray, ends: FloatArray, reach_m: float) -> BoolArray:
    """(R, M) obstacles ``rel`` (R, M, D) within ``reach_m`` of any of the points ``ends`` (R, S, D), all S at once
    on (R, S, M) coordinate planes (a prefilter: its reach has slack, so its own rounding never matters)."""
    d2 = np.zeros((ends.shape[0], ends.shape[1], rel.shape[1]))
    for d in range(rel.shape[2]):
        delta = rel[:, None, :, d] - ends[:, :, d, None]
        delta *= delta
        d2 += delta
    return np.asarray(np.logical_or.reduce(d2 <= reach_m * reach_m, axis=1), dtype=np.bool_)


def _near(
    positions_m: FloatArray, obstacles_m: FloatArray, mask: BoolArray | None, reach_m: float
) -> tuple[FloatArray, BoolArray]:
    """``clearance.near_obstacles`` (obstacles within ``reach_m``, relative to each agent, near ones first in index
    order, zero rows where ``valid`` is False), computed without einsum over the short coordinate axis (which costs
    about 8x the plain products at the study's (500, 95, 2)) and gathered by position instead of a sort.

    The same offsets; the squared distance is summed in coordinate order, which can differ from einsum's order in
    the last bit (3D) only for obstacles at the reach itself, where the callers' reaches have slack."""
    dim = obstacles_m.shape[2]
    rel = obstacles_m - positions_m[:, None, :]
    d2 = rel[:, :, 0] * rel[:, :, 0]
    for d in range(1, dim):
        d2 += rel[:, :, d] * rel[:, :, d]
    within = d2 <= reach_m * reach_m  # non-finite obstacles compare False
    if mask is not None:
        within &= mask
    return compact_rows(rel, within)


# 2D: the sums of two products written out are einsum's bit for bit (a sum of two terms has one rounding, in
# either order) and several times faster on the short coordinate axis; 3D keeps einsum and its order.


def _sq_norm(v: FloatArray) -> FloatArray:
    """(A, S) |v|^2 of (A, S, D) vectors."""
    if v.shape[2] == 2:
        return np.asarray(v[:, :, 0] * v[:, :, 0] + v[:, :, 1] * v[:, :, 1], dtype=np.float64)
    return np.asarray(np.einsum("akd,akd->ak", v, v), dtype=np.float64)


def _cosines(dirs: FloatArray, units: FloatArray) -> FloatArray:
    """(A, K) dirs_a . units_k of (A, D) and (K, D) (not @: BLAS rounding differs with A)."""
    if dirs.shape[1] == 2:
        return np.asarray(dirs[:, 0, None] * units[None, :, 0] + dirs[:, 1, None] * units[None, :, 1], dtype=np.float64)
    return np.asarray(np.einsum("ad,kd->ak", dirs, units), dtype=np.float64)
