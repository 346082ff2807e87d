"""bapf-nav's single-agent prologue (the service's ``step``): target, sight, trail and progress rules of one agent.

``BapfNavPlanner._start`` runs these rules on (A,) arrays; at one agent each of its numpy calls costs more than
the arithmetic, so ``SingleStart`` runs them on Python floats and the line of sight (``LineOfSight.blocked``)
on 1-D arrays, with no group loop and no floating-point error state to switch (the caller checks the numbers are
finite first; non-finite or absurdly large ones take the batch test). Every value comes from the same
floating-point operations as in the batch path: Python's float arithmetic and ``math.sqrt`` are IEEE double like
numpy's on single values; sums of D products stay einsum calls on the same layouts (numpy's einsum does not sum
three products left to right, and a build may fuse its multiply-adds), except where only a comparison far from
its threshold is needed (the trail).
tests/planning/test_planning_navsingle.py compares both with the batch path.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.planning.area import zones_block_line, zones_bound_lines
from apf_companion.planning.navone import einsum
from apf_companion.planning.navsight import _AROUND_SLACK_M, _SIGHT_FIRST, _SURFACE_M, LineOfSight
from apf_companion.planning.navstate import TRAIL, GiveUp, NavMode, NavState
from apf_companion.planning.params import PlannerParams

__all__ = ["FIELD_AGE_CAP", "SightLine", "SingleStart", "age_field"]

FloatArray = npt.NDArray[np.float64]

#: Smallest normal float64 (the divisor for an agent on its goal, as in ``LineOfSight.blocked``).
_TINY = float(np.finfo(np.float64).tiny)
#: Squared distances up to this are safe to square and add again (no overflow): beyond, the batch test decides.
_SANE_M2 = 1e300
#: Relative band around the trail spacing where the batch path's einsum decides (``SingleStart._record``).
_ULPS = 1e-12
#: ``NavState.since_*`` are int32: a count stops there (any count that high has already given up or gone stale).
_INT32_MAX = 2**31 - 1
#: Ages of fields stop counting here (any age >= ``nav_replan_steps`` means stale; ``NavState.since_field``).
FIELD_AGE_CAP = 2**30
_DIRECT = int(NavMode.DIRECT)
_ESCAPE = int(NavMode.ESCAPE)
_GAVE_UP = int(NavMode.GAVE_UP)


class SightLine:
    """``LineOfSight.blocked`` of one agent on 1-D arrays (its docstring has the rule), the same result.

    Parameters
    ----------
    params : the planner's parameters; clearance_m : C [m].
    """

    def __init__(self, params: PlannerParams, clearance_m: float) -> None:
        self._sight_m = params.nav_sight_m
        self._near_m = min(params.nav_sight_points_m, params.nav_sight_m)
        self._step_m = params.step_m
        self._c2 = clearance_m * clearance_m
        self._surface2 = _SURFACE_M * _SURFACE_M
        self._first = _SIGHT_FIRST
        self._around2 = (clearance_m + _SURFACE_M + _AROUND_SLACK_M) ** 2
        # Caps of the two pieces' coordinates along the line: the whole piece (inf: no cap) and its first
        # ``_near_m`` (``_pieces``).
        self._caps = np.array([[math.inf], [self._near_m]])

    def __call__(self, rel_m: FloatArray, obstacles_m: FloatArray, goal_vec_m: FloatArray, g0_m: float) -> bool:
        """Whether the line is blocked. ``rel_m`` (M, D) obstacles minus the agent, ``obstacles_m`` (M, D), all
        finite, |rel|^2 <= ``_SANE_M2``; ``goal_vec_m`` (D,) target minus agent, ``g0_m`` its length (finite)."""
        n_obs = rel_m.shape[0]
        if self._sight_m <= 0.0 or n_obs == 0:
            return False
        unit = goal_vec_m / max(g0_m, _TINY)
        # The einsum calls are the batch path's, on one row (the same reduction kernels, whatever the build).
        along = einsum("amd,ad->am", rel_m[None], unit[None])[0]
        off2s = self._pieces(rel_m, along, unit, g0_m)
        hits = off2s < self._c2
        if self._near_m > 0.0 and bool(np.logical_or.reduce(hits[1])):
            return True  # any point near the agent
        off2, hit = off2s[0], hits[0]
        picks = hit.nonzero()[0]
        if picks.size == 0:
            return False
        first = min(self._first, n_obs)
        if picks.size > first:  # the first hits along the line: the batch path's call on the same numbers
            order = np.where(hit, along, math.inf)
            picks = np.argpartition(order, first - 1)[:first]
        # Fewer hits than ``first``: the batch path picks them all (its other picks are not hits).
        # A pick's neighbours lie within C + surface_m of the line (off2 is the squared distance to it; its
        # rounding is relative to these few metres): only they are compared, with the batch path's arithmetic.
        around = obstacles_m[off2 < self._around2]
        gap = around[None, None, :, :] - obstacles_m.take(picks, axis=0)[None, :, None, :]  # (1, P, Q, D)
        d2 = einsum("sfmd,sfmd->sfm", gap, gap)[0]
        close = d2 < self._surface2
        close &= d2 > 0.0
        return bool(np.logical_or.reduce(np.add.reduce(close, axis=1) >= 2))

    def _pieces(self, rel_m: FloatArray, along: FloatArray, unit: FloatArray, g0_m: float) -> FloatArray:
        """(2, M) squared distances of the points to the line's piece from one step ahead to ``nav_sight_m`` (row
        0) and to its first ``nav_sight_points_m`` (row 1), as the batch path's two ``_line_hits`` have them.

        Row 1's coordinates are row 0's capped at ``_near_m``: min(clip(a, min(s, e), e), n) = clip(a, min(s, e'),
        e') with e' = min(e, n) (the batch path's near piece), exactly, as min and max round nothing."""
        end = min(g0_m, self._sight_m)
        start = min(self._step_m, end)
        t = np.maximum(along, start)  # np.clip(along, start, end) without its Python wrapper
        np.minimum(t, end, out=t)
        t2 = np.minimum(t, self._caps)  # (2, M)
        off = rel_m - t2[:, :, None] * unit
        off2: FloatArray = einsum("amd,amd->am", off, off)
        return off2


class SingleStart:
    """``BapfNavPlanner._start`` of one agent (module docstring): the goal vector and distance after the sight,
    trail and progress rules, with the same state updates.

    Parameters
    ----------
    params : the planner's parameters; batch_sight : the planner's batch line-of-sight test (it decides where the
    numbers are not finite); sight : the single-agent sight test; trail_spacing_m : ``NavState.record``'s
    spacing [m]; progress_share : a new closest approach beats the old one by this share of a step.
    """

    def __init__(
        self,
        params: PlannerParams,
        batch_sight: LineOfSight,
        sight: SightLine,
        trail_spacing_m: float,
        progress_share: float,
    ) -> None:
        self._batch_sight = batch_sight
        self._sight = sight
        #: The zones that block a line (``area.zones_block_line``, as ``LineOfSight.blocked``), kept at C.
        self._area, self._keepouts = params.nav_area_ne_m, params.nav_keepout_ne_m
        self._zones = zones_bound_lines(self._area, self._keepouts)
        self._margin_m = batch_sight.clearance_m
        self._step_m = params.step_m
        self._patience = params.nav_patience_steps
        self._spacing2 = trail_spacing_m * trail_spacing_m
        self._progress_m = progress_share * params.step_m

    def __call__(
        self, position_m: FloatArray, target_m: FloatArray, obstacles_m: FloatArray, state: NavState
    ) -> tuple[FloatArray, float, FloatArray, FloatArray]:
        """Target minus position (D,) and its length g0, and the obstacles minus the agent (M, D) with their
        squared distances (M,) (``navone.DirectStep`` takes them). ``state``: one row, updated in place."""
        goal_vec = target_m - position_m
        g0 = math.sqrt(float(einsum("ad,ad->a", goal_vec[None], goal_vec[None])[0]))  # the batch path's call
        rel = obstacles_m - position_m
        r2 = einsum("nd,nd->n", rel, rel)
        mode = int(state.mode[0])
        hit_m = float(state.hit_dist_m[0])
        looking = mode == _DIRECT or (mode == _ESCAPE and g0 < hit_m - self._step_m)
        blocked = looking and self._blocked(position_m, target_m, obstacles_m, rel, r2, goal_vec, g0)
        self._record(position_m, state)
        self._progress(state, mode, hit_m, g0, blocked)
        return goal_vec, g0, rel, r2

    def _blocked(
        self,
        position_m: FloatArray,
        target_m: FloatArray,
        obstacles_m: FloatArray,
        rel: FloatArray,
        r2: FloatArray,
        goal_vec: FloatArray,
        g0: float,
    ) -> bool:
        """The line of sight; non-finite or huge numbers go to the batch test (its floating-point state)."""
        total = float(np.add.reduce(r2)) if r2.shape[0] else 0.0
        if math.isfinite(g0) and total <= _SANE_M2:  # also False for NaN
            if self._sight(rel, obstacles_m, goal_vec, g0):
                return True
            start, end = position_m[None, :2], target_m[None, :2]
            return self._zones and bool(zones_block_line(self._area, self._keepouts, start, end, self._margin_m)[0])
        every = np.ones(1, dtype=bool)
        return bool(self._batch_sight.blocked(every, position_m[None], target_m[None], obstacles_m[None], None)[0])

    def _record(self, position_m: FloatArray, state: NavState) -> None:
        """``NavState.record`` of one agent. Its squared distance in Python floats is within a few ulp of the
        batch path's einsum (which may fuse a multiply-add, e.g. on ARM); near the spacing, the einsum decides."""
        slot = int(state.trail_next[0])
        last = state.trail_m[0, (slot - 1) % TRAIL]
        last_n, last_e = last.tolist()
        north, east = position_m[:2].tolist()
        dn, de = north - last_n, east - last_e
        dist2 = dn * dn + de * de
        if abs(dist2 - self._spacing2) <= _ULPS * self._spacing2:
            delta = position_m[None, :2] - last[None]
            dist2 = float(einsum("ad,ad->a", delta, delta)[0])
        if not dist2 < self._spacing2:  # NaN (no point yet): record
            state.trail_m[0, slot] = position_m[:2]
            state.trail_next[0] = (slot + 1) % TRAIL

    def _progress(self, state: NavState, mode: int, hit_m: float, g0: float, blocked: bool) -> None:
        """``BapfNavPlanner._progress`` of one agent; ``mode`` and ``hit_m`` as they were before the step."""
        if g0 < float(state.best_dist_m[0]) - self._progress_m:
            state.best_dist_m[0] = g0
            since = 0
        else:
            since = min(int(state.since_best[0]) + 1, _INT32_MAX)
        state.since_best[0] = since
        if mode == _ESCAPE and g0 < hit_m - self._step_m and not blocked:
            mode = _DIRECT
        elif mode == _DIRECT and blocked:
            mode = _ESCAPE
            state.hit_dist_m[0] = g0
        if since > self._patience:
            if mode != _GAVE_UP:
                state.gave_up[0] = GiveUp.NO_PROGRESS
            mode = _GAVE_UP
        state.mode[0] = mode


def age_field(state: NavState) -> None:
    """``bapfnav._age_fields`` of one agent: a kept field ages, capped (no int32 overflow)."""
    age = int(state.since_field[0])
    if age < FIELD_AGE_CAP:
        state.since_field[0] = age + 1
