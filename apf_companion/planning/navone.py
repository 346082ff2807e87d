"""bapf-nav's single-agent DIRECT step (the service's ``step``) in few numpy calls: the same decision, bit for bit.

At one agent a step is numpy's per-call cost, not arithmetic (about 0.5 us per call on small arrays), so this
path computes what ``BapfNavPlanner._plan`` computes for a DIRECT agent with a third of the calls:

- the moves, the agent itself (a zero-length move) and the look-ahead probes are the columns of one (D, M, J)
  array program over the M near obstacles, so each operation covers every axis and segment at once
  (``add.reduce`` over the leading axis adds the D products in the order of the batch path's per-axis loop);
- the clearance terms at the points and at the agent are one (M, K + 1) array, and its column minimum gives the
  agent's nearest obstacle (d0) as well;
- per-agent quantities (the goal distance, cost at the agent, the turn hold) are Python floats.

Each value comes from the same floating-point operations, in the same order, as in the batch path (the einsum
reductions are the same calls on arrays of the same layout: numpy's einsum does not sum three products left to
right, so it is not replaced by another formula). ``tests/planning/test_planning_nav_digest.py`` pins the
decisions; tests/planning/test_planning_nav.py checks ``step`` against ``step_batch`` rows.

It returns None where the agent enters ESCAPE (no point passes, some move is feasible): the caller's escape path
(``navescapeone.EscapeStep``) then decides on the same, untouched state, with this step's geometry (``trapped``).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from apf_companion.planning.clearance import (
    clearance_terms,
    lookahead_probes,
    sweep_sq_inplace,
    sweep_term_inplace,
)
from apf_companion.planning.decision import Decision, DecisionReason
from apf_companion.planning.params import PlannerParams

__all__ = ["DirectStep", "einsum"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]


def _c_einsum() -> Callable[..., FloatArray]:
    """``np.einsum`` without ``optimize`` calls this C function behind a Python wrapper (about 0.7 us a call):
    the same call, kernels and results without the wrapper; ``np.einsum`` itself where numpy has no such name."""
    try:
        module = importlib.import_module("numpy._core.multiarray")  # numpy >= 2
    except ImportError:
        return np.einsum
    found: Callable[..., FloatArray] = getattr(module, "c_einsum", np.einsum)
    return found


#: The einsum calls of the single-agent path (``_c_einsum``).
einsum = _c_einsum()

#: Smallest normal float64 (the divisor of zero-length segments, as in ``clearance.MoveSweep``).
_TINY = float(np.finfo(np.float64).tiny)
_INF = math.inf


class DirectStep:
    """The DIRECT step of one agent (module docstring).

    Parameters
    ----------
    params : the planner's parameters.
    offsets_m : (K, D) bacteria offsets [m]; units : (K, D) the same as unit vectors.
    clearance_m : C [m]; reach_m : obstacles farther than this from the agent cannot matter [m].
    """

    def __init__(
        self, params: PlannerParams, offsets_m: FloatArray, units: FloatArray, clearance_m: float, reach_m: float
    ) -> None:
        p = params
        n_points, dim = offsets_m.shape
        self._offsets = offsets_m
        self._units = units
        # The turn cosines from each previous move (``NavState.prev_dir`` is a row of ``units``): the batch path's
        # einsum on that row, once per row here instead of once per step.
        self._cos_after = {
            tuple(u): np.einsum("ad,kd->ak", units[j : j + 1], units)[0] for j, u in enumerate(units.tolist())
        }
        self._n = n_points
        self._c2 = clearance_m**2
        self._floor2 = (p.vehicle_radius_m + p.safety_margin_m) ** 2
        self._reach2 = reach_m * reach_m
        self._cos_hold = math.cos(math.radians(p.nav_hold_angle_deg))
        self._hold_ratio = p.nav_hold_ratio
        self._decay_per_m2 = p.nav_clearance_decay_per_m2
        self._gain = p.nav_clearance_gain_m
        self._lookahead_m = p.nav_lookahead_m
        self._penalty_m = p.nav_lookahead_penalty_m
        self._probing = p.nav_lookahead_m > 0.0 and p.nav_lookahead_penalty_m > 0.0
        o2 = np.einsum("kd,kd->k", offsets_m, offsets_m)
        # Columns: the K moves (start 0, vector o_k), the agent (start 0, vector 0), the K probes (start o_k).
        self._end_o2 = np.concatenate([o2, [0.0]])  # (K + 1,) |o|^2 of the end points, the agent's is 0
        self._move_vectors = np.concatenate([offsets_m.T, np.zeros((dim, 1))], axis=1)  # (D, K + 1)
        self._move_v2 = np.concatenate([o2, [_TINY]])  # zero length: t = 0 (the agent's column)
        self._starts = np.concatenate([np.zeros((dim, n_points + 1)), offsets_m.T], axis=1)[:, None, :]
        # Every segment's vector (D, 2 K + 1) and |v|^2: the moves' columns fixed, the probes' written per step.
        self._vectors = np.concatenate([self._move_vectors, np.zeros((dim, n_points))], axis=1)
        self._v2 = np.concatenate([self._move_v2, np.zeros(n_points)])
        #: The geometry of the last step that returned None to enter ESCAPE (``plain_geometry``'s values: the
        #: look-ahead does not change them), None where it had no near obstacle.
        self.trapped: tuple[BoolArray, FloatArray, FloatArray, float] | None = None

    def __call__(
        self,
        position_m: FloatArray,
        rel_m: FloatArray,
        d2_m2: FloatArray,
        goal_vec_m: FloatArray,
        g0_m: float,
        prev_dir: FloatArray,
    ) -> Decision | None:
        """The step of an agent in DIRECT mode, or None where the batch path must decide (module docstring).

        ``position_m`` (D,) [m]; ``rel_m`` (N, D) the obstacles minus the position [m] and ``d2_m2`` (N,) their
        squared lengths, einsum("nd,nd->n") (the batch path's |rel|^2: not a left-to-right sum in 3D);
        ``goal_vec_m`` (D,) target minus position and ``g0_m`` its length [m]; ``prev_dir`` (1, D) the unit
        direction of the last move (zeros: none). The caller records the move (``NavState.prev_dir``)."""
        to_goal = goal_vec_m - self._offsets  # (K, D)
        g_k = np.sqrt(einsum("kd,kd->k", to_goal, to_goal))
        rel, d2 = rel_m, d2_m2
        near = (d2 <= self._reach2).nonzero()[0]
        seg2 = None
        if near.size == 0:
            feasible = np.ones(self._n, dtype=bool)
            cost, cost0 = g_k + 0.0 + 0.0, g0_m + 0.0  # the batch path adds its zero terms too
        else:
            probes = lookahead_probes(to_goal, g_k, self._lookahead_m) if self._probing else None
            feasible, seg2, clear_k, clear_0, look_k = self._geometry(rel.take(near, axis=0), d2[near], probes)
            cost = g_k + clear_k
            if look_k is not None:
                cost += look_k
            cost0 = g0_m + clear_0
        passing = feasible & (cost < cost0)
        n_passing = int(np.count_nonzero(passing))
        scores = np.where(passing, cost, _INF)
        if n_passing > 0:
            chosen = self.choose(scores, cost, cost0, passing, prev_dir)
        elif seg2 is None or bool(feasible.any()):  # entering ESCAPE: the caller's escape rules
            self.trapped = None if seg2 is None else (feasible, seg2, clear_k, clear_0)
            return None
        else:
            chosen = self.squeeze_out(seg2)
        if chosen < 0:
            return Decision(next_point_m=None, reason=DecisionReason.LOCAL_MINIMUM, n_safe=0, candidate_cost=scores)
        return Decision(
            next_point_m=position_m + self._offsets[chosen],
            reason=DecisionReason.GREEDY,
            chosen_index=chosen,
            n_passing=n_passing,
            n_safe=int(np.count_nonzero(feasible)),
            candidate_cost=scores,
        )

    def plain_geometry(self, rel_m: FloatArray, d2_m2: FloatArray) -> tuple[BoolArray, FloatArray, FloatArray, float]:
        """Feasible moves (K,), their swept squared clearance (K,) and the clearance terms at the points (K,) and
        the agent of an agent that does not look ahead (ESCAPE mode: ``navgeometry.MoveGeometry`` with ``direct``
        False); ``rel_m`` and ``d2_m2`` as in ``__call__``."""
        near = (d2_m2 <= self._reach2).nonzero()[0]
        if near.size == 0:  # the batch path's values without near obstacles
            return np.ones(self._n, dtype=bool), np.full(self._n, _INF), np.zeros(self._n), 0.0
        feasible, seg2, clear_k, clear_0, _ = self._geometry(rel_m.take(near, axis=0), d2_m2[near], None)
        return feasible, seg2, clear_k, clear_0

    def _geometry(
        self, rel: FloatArray, r2: FloatArray, probes: FloatArray | None
    ) -> tuple[BoolArray, FloatArray, FloatArray, float, FloatArray | None]:
        """Feasible moves (K,), their swept squared clearance (K,), clearance terms at the points (K,) and the
        agent, look-ahead penalties (K,) or None. ``rel`` (M, D), M > 0: the near obstacles minus the agent;
        ``r2`` (M,) their |rel|^2."""
        n = self._n
        if probes is None:  # every segment starts at the agent: |obstacle - start|^2 is one number per obstacle
            rel_t = rel.T.copy()  # (D, M) contiguous: the broadcast products run along contiguous rows
            dot = _axis_sum(rel_t[:, :, None] * self._move_vectors[:, None, :])
            clear_k, clear_0, nearest = self._clearance(dot, r2)  # before _closest_from consumes dot
            swept = _closest_from(dot, _axis_sum(rel_t * rel_t), self._move_v2)
        else:
            # The probes' columns of the step's segment vectors and |v|^2, written into the kept buffers (only read
            # below: the results are new arrays).
            vectors, v2 = self._vectors, self._v2
            vectors[:, n + 1 :] = probes.T
            probe_v2 = einsum("kd,kd->k", probes, probes, out=v2[n + 1 :])
            np.maximum(probe_v2, _TINY, out=probe_v2)
            dot, d2 = _segments(rel, self._starts, vectors)
            clear_k, clear_0, nearest = self._clearance(dot[:, : n + 1], r2)  # before _closest consumes dot
            swept = _closest(dot, d2, v2)
        seg2 = swept[:n]
        d0 = float(nearest[n])
        # Inside the clearance (d0 < C^2): get no closer along the move and end farther out.
        feasible = (seg2 >= d0) & (nearest[:n] > d0) if d0 < self._c2 else seg2 >= self._c2
        if probes is None:
            return feasible, seg2, clear_k, clear_0, None
        # The probe comes closer than the clearance: the penalty.
        return feasible, seg2, clear_k, clear_0, np.where(swept[n + 1 :] < self._c2, self._penalty_m, 0.0)

    def _clearance(self, dot: FloatArray, r2: FloatArray) -> tuple[FloatArray, float, FloatArray]:
        """The clearance terms at the K points (K,) and at the agent, and the squared distance of the nearest
        obstacle to each point and the agent (K + 1,), from ``dot`` (M, K + 1) rel . o (the agent's o = 0)."""
        n = self._n
        # Squared distance of each obstacle to the end points and the agent: |rel|^2 - 2 rel.o + |o|^2.
        ends = dot * -2.0
        ends += r2[:, None]
        ends += self._end_o2
        np.maximum(ends, 0.0, out=ends)
        nearest = np.minimum.reduce(ends, axis=0)  # (K + 1,); the agent's: d0
        terms = clearance_terms(ends, self._decay_per_m2, self._gain)
        clear_k = np.add.reduce(terms, axis=0)[:n]
        clear_0 = float(np.add.reduce(terms[:, n]))  # pairwise, as the batch path's row sum
        return clear_k, clear_0, nearest

    def squeeze_out(self, seg2: FloatArray) -> int:
        """Boxed in (``BapfNavPlanner._squeeze_out``): the move that keeps the most clearance, if that keeps
        radius + safety margin, else -1."""
        room = np.where(seg2 >= self._floor2, seg2, -_INF)
        widest = int(room.argmax())
        return widest if math.isfinite(room[widest]) else -1

    def choose(
        self, scores: FloatArray, cost: FloatArray, cost0: float, passing: BoolArray, prev_dir: FloatArray
    ) -> int:
        """Best passing point with the turn hysteresis (``BapfNavPlanner._choose``); some point passes."""
        best = int(scores.argmin())
        last = tuple(prev_dir[0].tolist())
        if not any(last):  # no previous move (a float is false only at +-0.0; NaN counts as a move, as c != 0.0)
            return best
        cos_turn = self._cos_after.get(last)
        if cos_turn is None:  # not a move of this planner's (a state from elsewhere): the batch path's call
            cos_turn = np.einsum("ad,kd->ak", prev_dir, self._units)[0]
        if not cos_turn[best] < self._cos_hold:
            return best
        held = np.where(passing & (cos_turn >= self._cos_hold), cost, _INF)
        alt = int(held.argmin())
        held_alt = float(held[alt])
        if not math.isfinite(held_alt):
            return best
        # Python floats: inf - inf (cost0 = inf) is NaN without a floating-point warning, and NaN < x is False.
        gain_best = cost0 - float(scores[best])
        gain_alt = cost0 - held_alt
        return alt if gain_best < self._hold_ratio * gain_alt else best


def _segments(rel: FloatArray, starts: FloatArray, vectors: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(M, J) (obstacle - start_j) . v_j and |obstacle - start_j|^2 for ``rel`` (M, D), ``starts`` (D, 1, J) and
    ``vectors`` (D, J)."""
    seg = rel.T.copy()[:, :, None] - starts  # (D, M, J): obstacle minus segment start, per axis
    d2 = _axis_sum(seg * seg)
    seg *= vectors[:, None, :]
    return _axis_sum(seg), d2


def _axis_sum(per_axis: FloatArray) -> FloatArray:
    """(M, J) sum over the leading axis of (D, M, J), left to right as the batch path's per-axis loop."""
    out: FloatArray = per_axis[0] + per_axis[1]
    for d in range(2, per_axis.shape[0]):
        out += per_axis[d]
    return out


def _closest_from(dot: FloatArray, r2: FloatArray, v2: FloatArray) -> FloatArray:
    """``_closest`` of segments that all start at the agent, from (M,) ``r2`` = |rel|^2 (left to right over the
    axes, as ``_segments`` has it): ``sweep_sq_inplace``'s operations, its last one broadcast (``dot`` is
    consumed)."""
    sweep_term_inplace(dot, v2)
    np.subtract(r2[:, None], dot, out=dot)
    swept: FloatArray = np.minimum.reduce(dot, axis=0)
    return np.maximum(swept, 0.0, out=swept)


def _closest(dot: FloatArray, d2: FloatArray, v2: FloatArray) -> FloatArray:
    """(J,) min over the obstacles of the squared distance to each segment (``dot`` and ``d2`` are consumed):
    |rel - t v|^2 = |rel|^2 - t (2 rel.v - t |v|^2) with t in [0, 1], as ``clearance.MoveSweep``."""
    sweep_sq_inplace(dot, d2, v2)
    swept: FloatArray = np.minimum.reduce(d2, axis=0)
    return np.maximum(swept, 0.0, out=swept)  # = the min of the clipped values, on J numbers instead of M J
