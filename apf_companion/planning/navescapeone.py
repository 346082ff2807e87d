"""bapf-nav's single-agent ESCAPE step (the service's ``step``): ``BapfNavPlanner._decide`` and
``EscapeMaps.potentials`` of one agent on 1-D arrays, the same decisions, fields and values, bit for bit.

``EscapeMaps`` works on rows of agents: per-row Python loops, object arrays of fields stacked for sampling, and
(R, ...) temporaries. At one agent those cost more than the arithmetic, so ``FieldOne`` runs the same rules
(stale, ``outdated``, stall and dead-end refreshes, carry-over, trail closure of edge cells, the ``lost`` check,
the occupancy and field memos) on one agent's arrays, and does not compute twice what the batch path does: a
field sampled at the candidate points in a step (for the ``lost`` check, the ``outdated`` check's value at the
agent, the potential) is sampled once in that step, and the edge cells the trail closes are kept with their exact
input (the grid's corner and the trail). ``FieldSampler`` samples one field without the batch path's stacks and,
where every corner is inside the grid and finite, without its masks. ``EscapeStep`` is the decision around it.
Every value comes from the same floating-point operations as in the batch path (elementwise numpy arithmetic does
not depend on the array's shape; sums of products stay the batch path's einsum calls on the same layouts).
tests/planning/test_planning_navescapeone.py compares both paths, decisions and state, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.planning.decision import Decision, DecisionReason
from apf_companion.planning.navescape import (
    _OUTDATED_AGE,
    EscapeMaps,
    mark_dead_end,
    own_cell_blocked,
)
from apf_companion.planning.navone import DirectStep
from apf_companion.planning.navrefreshone import RefreshOne
from apf_companion.planning.navsingle import age_field
from apf_companion.planning.navstate import GiveUp, NavField, NavMode, NavState

__all__ = ["EscapeStep", "FieldOne", "FieldSampler"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]

_INF = math.inf
_GAVE_UP = int(NavMode.GAVE_UP)


class FieldOne:
    """The escape potential of one agent (``EscapeMaps.potentials`` on ``NavState`` row 0; module docstring).

    Parameters
    ----------
    maps : the planner's escape maps (grid, parameters, edge cells).
    """

    def __init__(self, maps: EscapeMaps) -> None:
        p = maps.params
        self._grid = maps.grid
        self._n = maps.grid.n
        self._h = maps.grid.cell_m
        self._dim = p.dim
        self._replan = p.nav_replan_steps
        self._sight2 = p.nav_sight_m**2
        self._clearance_m = maps.clearance_m
        self._slack_m = 2.0 * maps.clearance_m + maps.grid.cell_m
        offsets = maps._offsets
        # The candidate points and the agent (a zero offset), as ``EscapeMaps.geodesic`` stacks them.
        self._around = np.vstack([offsets, np.zeros((1, offsets.shape[1]))])
        self._around_t = np.vstack([offsets[:, :2], np.zeros((1, 2))]).T.copy()  # (2, K + 1): rows north, east
        self._offsets_xy = offsets[:, :2]
        self._sample = FieldSampler(maps.grid.n, maps.grid.cell_m)
        #: Fields sampled at the points in this step (``_sampled``): field, corner as bytes, values.
        self._samples: list[tuple[FloatArray, bytes, FloatArray]] = []
        self._refresh = RefreshOne(maps, self._sampled)

    def potentials(
        self,
        position_m: FloatArray,
        target_m: FloatArray,
        obstacles_m: FloatArray,
        d2_m2: FloatArray,
        state: NavState,
        feasible: BoolArray,
        clear_k: FloatArray,
        clear_0: float,
    ) -> tuple[FloatArray, float, BoolArray]:
        """Geodesic potential at the points (K,) and the agent, and which points pass (``EscapeMaps.potentials``).
        ``d2_m2`` (M,): the obstacles' squared distances to the agent, einsum("nd,nd->n") as ``outdated`` has
        them; position and target finite."""
        self._samples = []
        field = state.field[0]
        age = int(state.since_field[0])
        stale = field is None or age >= self._replan
        if not stale and age >= _OUTDATED_AGE:
            stale = self._outdated(field, position_m, obstacles_m, d2_m2)
        values = self._refresh(position_m, target_m, obstacles_m, state) if stale else None
        g_k, g0 = self._geodesic(position_m, target_m, state.field[0], values)
        ok = feasible & (g_k + clear_k < g0 + clear_0)
        dead = not ok.any()
        if dead and not stale:  # stalled on a potential that may be stale: recompute once with what is known now
            values = self._refresh(position_m, target_m, obstacles_m, state)
            if not _same_field(field, state.field[0]):  # the same field (memo): the same values, still dead
                g_k, g0 = self._geodesic(position_m, target_m, state.field[0], values)
                ok = feasible & (g_k + clear_k < g0 + clear_0)
                dead = not ok.any()
        # Still nothing: mark the refused downhill cells and recompute once, where a cell was newly marked.
        if dead and self._mark_dead_ends(position_m, state.field[0], feasible, g_k, g0):
            values = self._refresh(position_m, target_m, obstacles_m, state)
            g_k, g0 = self._geodesic(position_m, target_m, state.field[0], values)
            ok = feasible & (g_k + clear_k < g0 + clear_0)
        return g_k, g0, ok

    def _outdated(self, field: NavField, position_m: FloatArray, obstacles_m: FloatArray, d2_m2: FloatArray) -> bool:
        """``EscapeMaps.outdated`` of one agent."""
        near = d2_m2 <= self._sight2  # non-finite rows compare False
        if self._dim == 3:
            near &= np.abs(obstacles_m[:, 2] - position_m[2]) <= self._clearance_m
        idx = near.nonzero()[0]
        if idx.size == 0:
            return False
        n = self._n
        # ``NavGrid.cell_of`` on finite points (``near`` holds only finite ones): no NaN to replace.
        ij = np.floor((obstacles_m[idx, :2] - field.origin_m) / self._h)
        np.clip(ij, -1, n, out=ij)
        cij = ij.astype(np.intp)
        ci, cj = cij[:, 0], cij[:, 1]
        inside = ((ci >= 0) & (ci < n) & (cj >= 0) & (cj < n)).nonzero()[0]
        cells = ci[inside] * n + cj[inside]
        new = (~field.blocked[cells]).nonzero()[0]
        if new.size == 0:
            return False
        # The field at the agent: the value ``_geodesic`` samples next (the same point, kept for this step).
        here = float(self._sampled(field.origin_m, field.dist_m, position_m[:2])[-1])
        if not here < np.inf:  # inf (enclosed or off the grid): outdated
            return True
        way = np.sqrt(d2_m2[idx[inside[new]]]) + field.dist_m[cells[new]]
        return bool((way <= here + self._slack_m).any())

    def _mark_dead_ends(
        self, position_m: FloatArray, field: NavField, feasible: BoolArray, g_k: FloatArray, g0: float
    ) -> bool:
        """``EscapeMaps.mark_dead_ends`` of one agent: whether a cell was newly blocked."""
        refused = ~feasible & (g_k < g0)
        if not refused.any():
            return False
        return mark_dead_end(self._grid, field, position_m[:2], position_m[:2] + self._offsets_xy[refused])

    def _geodesic(
        self, position_m: FloatArray, target_m: FloatArray, field: NavField, values: FloatArray | None
    ) -> tuple[FloatArray, float]:
        """``EscapeMaps.geodesic`` of one agent; ``values``: the field already sampled at the points (or None)."""
        if values is None:
            values = self._sampled(field.origin_m, field.dist_m, position_m[:2])
        if self._dim == 3:
            pts = position_m + self._around
            dz = pts[:, 2] - target_m[2]
            values = np.sqrt(values * values + dz * dz)
        return values[:-1], float(values[-1])

    def _sampled(self, origin_m: FloatArray, dist_m: FloatArray, xy_m: FloatArray) -> FloatArray:
        """``_sample`` at this step's points and the agent (``xy_m``: its north, east): a field sampled before in
        this step (the same field object, never written to, in the same frame) gives the same values again."""
        origin = origin_m.tobytes()
        for dist, frame, values in self._samples:
            if dist is dist_m and frame == origin:
                return values
        values = self._sample.at(origin_m, dist_m, xy_m[:, None] + self._around_t)  # (2, K + 1) points
        self._samples.append((dist_m, origin, values))
        return values


class FieldSampler:
    """``NavGrid.sample_many`` of one field (grid of ``n`` x ``n`` cells of ``cell_m``), on 1-D arrays."""

    def __init__(self, n: int, cell_m: float) -> None:
        self._n = n
        self._h = cell_m
        self._corner_di = np.array([[0], [0], [1], [1]], dtype=np.intp)  # the four corners' steps along i, j
        self._corner_dj = np.array([[0], [1], [0], [1]], dtype=np.intp)
        self._corner_flat = np.array([[0], [1], [n], [n + 1]], dtype=np.intp)  # the same four, as flat offsets
        # (1 - f, f) per axis as (0 + 1) - f and 0 - (-f): exact, so the weights are the batch path's.
        self._pair_base = np.array([1.0, 0.0])[:, None, None]
        self._pair_sign = np.array([1.0, -1.0])[:, None, None]  # times (2, P) fractions: (2, 2, P)

    def __call__(self, origin_m: FloatArray, dist_m: FloatArray, points_xy_m: FloatArray) -> FloatArray:
        """``NavGrid.sample_many`` of one field at points (P, 2) (``at`` on their transpose)."""
        return self.at(origin_m, dist_m, np.ascontiguousarray(points_xy_m.T))

    def at(self, origin_m: FloatArray, dist_m: FloatArray, points_t_m: FloatArray) -> FloatArray:
        """``NavGrid.sample_many`` of one field at points (2, P) (rows: north, east): the same arithmetic, corner
        by corner, on contiguous rows. Where every corner lies in the grid, the clamping changes no index and
        every point is inside; where every corner is also finite with a positive weight, the batch path's masks
        select nothing and its sums are these."""
        n = self._n
        rel = (points_t_m - origin_m[:, None]) / self._h - 0.5
        low = np.floor(rel).astype(np.intp)
        frac = rel - low  # never -0.0 (rel - floor(rel)), so every weight is +0.0 or more
        # Every corner index in [0, n - 1]: as unsigned, a negative index is huge.
        interior = int(np.maximum.reduce(low.view(np.uintp), axis=None)) <= n - 2
        if interior:
            val = dist_m[(low[0] * n + low[1]) + self._corner_flat]  # (4, P)
        else:  # the corners (i0, j0), (i0, j0 + 1), (i0 + 1, j0), (i0 + 1, j0 + 1), each index clamped
            ii = np.clip(low[0] + self._corner_di, 0, n - 1)
            ii *= n
            ii += np.clip(low[1] + self._corner_dj, 0, n - 1)
            val = dist_m[ii]
        pair = self._pair_sign * frac  # (2, 2, P): (f, -f) per axis
        np.subtract(self._pair_base, pair, out=pair)  # (1 - f, f) per axis
        w: FloatArray = (pair[:, None, 0] * pair[None, :, 1]).reshape(4, -1)  # wi * wj, corner by corner
        ok = np.isfinite(val)
        ok &= w > 0.0
        # Summed corner by corner in the batch path's order: a reduction over the leading axis adds the rows in
        # turn. Where the batch path masks a corner to 0.0, w * ok is +0.0 (w >= 0 and finite) and so is
        # (w * ok) * 0.0: the same terms.
        if interior and ok.all():
            fast: FloatArray = np.add.reduce(w * val, axis=0)
            fast /= np.add.reduce(w, axis=0)
            return fast
        weight = w * ok
        term = np.where(ok, val, 0.0)
        term *= weight
        num = np.add.reduce(term, axis=0)
        den = np.add.reduce(weight, axis=0)
        use = den > 0.0
        if not interior:
            inside = rel >= -0.5
            inside &= rel <= n - 0.5
            use &= np.logical_and.reduce(inside, axis=0)
        out: FloatArray = np.full(num.shape, np.inf)
        np.divide(num, den, out=out, where=use)
        return out


def _same_field(old: NavField | None, new: NavField | None) -> bool:
    """Whether ``new`` holds the potential of ``old``: the same distances (a memo hit) in the same frame."""
    if old is None or new is None:
        return False
    return new.dist_m is old.dist_m and new.origin_m.tolist() == old.origin_m.tolist()


class EscapeStep:
    """The ESCAPE step of one agent: ``BapfNavPlanner._decide`` with ``EscapeMaps.scores`` for an escaping agent
    (and one that enters ESCAPE now), the same decision and state updates.

    Parameters
    ----------
    maps : the planner's escape maps; direct : its single-agent DIRECT step (geometry, choice, squeeze-out);
    offsets_m : (K, D) bacteria offsets [m]; units : (K, D) the same as unit vectors.
    """

    def __init__(self, maps: EscapeMaps, direct: DirectStep, offsets_m: FloatArray, units: FloatArray) -> None:
        self._field = FieldOne(maps)
        self._grid = maps.grid
        self._direct = direct
        self._offsets = offsets_m
        self._units = units

    def __call__(
        self,
        position_m: FloatArray,
        target_m: FloatArray,
        obstacles_m: FloatArray,
        rel_m: FloatArray,
        d2_m2: FloatArray,
        state: NavState,
        trapped: tuple[BoolArray, FloatArray, FloatArray, float] | None = None,
    ) -> Decision:
        """The step; ``rel_m`` and ``d2_m2`` as ``navone.DirectStep`` takes them; ``trapped``: the geometry of a
        DIRECT step that found no passing point (None: computed here). Position and target finite."""
        geometry = self._direct.plain_geometry(rel_m, d2_m2) if trapped is None else trapped
        feasible, seg2, clear_k, clear_0 = geometry
        g_k, g0, ok = self._field.potentials(
            position_m, target_m, obstacles_m, d2_m2, state, feasible, clear_k, clear_0
        )
        if not ok.any():  # any feasible point down the potential (the clearance term may hold the agent)
            ok = feasible & (g_k < g0)
        cost = g_k + clear_k
        has_ok = bool(ok.any())  # then some feasible point has a finite potential (inf < x is False)
        cost0 = g0 + clear_0 if has_ok else _INF
        any_feasible = bool(feasible.any())
        # Every feasible point off the map's free cells: back out from inside the inflated obstacles, else give up.
        gave_up = False
        if any_feasible and not has_ok and not np.isfinite(g_k[feasible]).any():
            if math.isfinite(g0) or not own_cell_blocked(self._grid, state.field[0], position_m[:2]):
                gave_up = True
                state.mode[0] = _GAVE_UP
                state.gave_up[0] = GiveUp.NO_WAY
            else:
                ok, cost, cost0 = feasible, clear_k, _INF
        scores = np.where(ok, cost, _INF)
        n_passing = int(np.count_nonzero(ok))
        if gave_up:
            chosen = -1
        elif not any_feasible:
            chosen = self._direct.squeeze_out(seg2)
        elif n_passing > 0:
            chosen = self._direct.choose(scores, cost, cost0, ok, state.prev_dir)
        else:
            chosen = -1
        n_safe = int(np.count_nonzero(feasible))
        age_field(state)
        if chosen < 0:
            reason = DecisionReason.GAVE_UP if gave_up else DecisionReason.LOCAL_MINIMUM
            return Decision(next_point_m=None, reason=reason, n_passing=n_passing, n_safe=n_safe, candidate_cost=scores)
        state.prev_dir[0] = self._units[chosen]
        return Decision(
            next_point_m=position_m + self._offsets[chosen],
            reason=DecisionReason.GREEDY,
            chosen_index=chosen,
            n_passing=n_passing,
            n_safe=n_safe,
            candidate_cost=scores,
        )
