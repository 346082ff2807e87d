"""Clearance geometry of the product planners: which obstacles are near, and how close a straight move passes.

Every function works on a batch of A agents with obstacles relative to each agent (obstacle minus agent), so no
large coordinates are subtracted and the arrays stay small: the prefilter keeps only the obstacles within reach
of one move (step + clearance), usually a handful even when hundreds of points are remembered. The sweep test is
exact for a straight segment (closest point of the segment to each obstacle point), not an endpoint test.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = [
    "MoveSweep",
    "clearance_terms",
    "compact_rows",
    "lookahead_probes",
    "near_obstacles",
    "point_clearance_sq",
    "segment_clearance_sq",
    "segments_clearance_sq",
    "sweep_sq_inplace",
    "sweep_term_inplace",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Smallest normal float64: the divisor of zero-length probes (``MoveSweep``).
_TINY = float(np.finfo(np.float64).tiny)


def near_obstacles(
    positions_m: FloatArray, obstacles_m: FloatArray, mask: BoolArray | None, reach_m: float
) -> tuple[FloatArray, BoolArray]:
    """Obstacles within ``reach_m`` of each agent, relative to it, gathered to the smallest common width.

    Parameters
    ----------
    positions_m : (A, D) agents [m].
    obstacles_m : (A, N, D) obstacle points [m]; rows where ``mask`` is False are ignored (may be non-finite).
    mask : (A, N) known obstacles, or None for all.
    reach_m : keep obstacles at most this far away [m].

    Returns
    -------
    rel : (A, M, D) obstacle minus agent [m] (zero rows where ``valid`` is False).
    valid : (A, M) which rows of ``rel`` are real; M = the largest count over the agents (0 if none).
    """
    n_agents, n_obs, dim = obstacles_m.shape
    if n_obs == 0:
        return np.zeros((n_agents, 0, dim)), np.zeros((n_agents, 0), dtype=bool)
    rel = obstacles_m - positions_m[:, None, :]
    # Non-finite obstacles give inf or NaN here, never a floating-point error (squares are >= 0; NaN is quiet),
    # and compare False. 2D: the two products written out, einsum's sum bit for bit (one rounding, either order)
    # and about twice as fast at the study's groups of (16, 95, 2) (measured then); 3D keeps einsum and its order.
    if dim == 2:
        d2 = rel[:, :, 0] * rel[:, :, 0]
        d2 += rel[:, :, 1] * rel[:, :, 1]
    else:
        d2 = np.einsum("and,and->an", rel, rel)
    within = d2 <= reach_m * reach_m
    if mask is not None:
        within &= mask
    return compact_rows(rel, within)


def compact_rows(rel: FloatArray, keep: BoolArray) -> tuple[FloatArray, BoolArray]:
    """The rows ``keep`` of (A, N, D) ``rel`` first, in index order, as (A, W, D) and their (A, W) mask; W = the
    largest count (zero rows and False beyond each agent's count). Gathered by position (each kept row's slot is
    its rank among its agent's kept rows), not by a sort."""
    n_agents, _, dim = rel.shape
    if n_agents == 1:  # one agent (the service's step): its rows by index, all valid
        idx = np.flatnonzero(keep[0])
        return rel[:, idx], np.ones((1, idx.size), dtype=bool)
    rows, cols = np.nonzero(keep)  # row-major: each agent's rows in index order
    counts = np.bincount(rows, minlength=n_agents)
    width = int(counts.max()) if n_agents else 0
    starts = np.cumsum(counts) - counts
    slot = np.arange(rows.size) - starts[rows]
    gathered = np.zeros((n_agents, width, dim))
    valid = np.zeros((n_agents, width), dtype=bool)
    gathered[rows, slot] = rel[rows, cols]
    valid[rows, slot] = True
    return gathered, valid


def clearance_terms(dist_sq_m2: FloatArray, decay_per_m2: float, gain_m: float) -> FloatArray:
    """bapf-nav's clearance term gain * exp(-decay * d^2) of each squared distance: Eq. (2) at product scale,
    ``potentials.obstacle_potential`` with one temporary (the same operations)."""
    out = dist_sq_m2 * -decay_per_m2
    np.exp(out, out=out)
    out *= gain_m
    return out


def lookahead_probes(to_goal_m: FloatArray, g_k_m: FloatArray, lookahead_m: float) -> FloatArray:
    """(..., K, D) bapf-nav's look-ahead probes: from each point towards the goal (``to_goal_m``, of length
    ``g_k_m``), ``lookahead_m`` long or to the goal. A point on the goal (g = 0) gets a zero probe:
    min(g, L) / max(g, tiny) = 0 there, no 0/0."""
    scale = np.minimum(g_k_m, lookahead_m)
    scale /= np.maximum(g_k_m, _TINY)
    return to_goal_m * scale[..., None]


def point_clearance_sq(rel_m: FloatArray, valid: BoolArray) -> FloatArray:
    """(A,) squared distance from each agent to its nearest valid obstacle (inf if none) [m^2]."""
    d2 = np.where(valid, np.einsum("amd,amd->am", rel_m, rel_m), np.inf)
    return np.asarray(np.min(d2, axis=1, initial=np.inf), dtype=np.float64)


def _axes(rel_m: FloatArray) -> list[FloatArray]:
    """The D coordinate planes of (A, M, D) points as contiguous (M, A) arrays.

    Work arrays are laid out (obstacle, agent, point), so every ufunc runs along the contiguous axis of the N_b
    points and reductions over obstacles combine whole (A, K) slices (numpy is slow on short inner axes).
    """
    return [np.ascontiguousarray(rel_m[:, :, d].T) for d in range(rel_m.shape[2])]


def _invalid_to_inf(d2: FloatArray, valid: BoolArray) -> None:
    """Set the (M, A, K) rows of padding obstacles to +inf, in place."""
    if not valid.all():  # e.g. one agent from near_obstacles: every row is real
        np.copyto(d2, np.inf, where=~valid.T[:, :, None])


def segment_clearance_sq(rel_m: FloatArray, valid: BoolArray, offsets_m: FloatArray) -> FloatArray:
    """Squared distance from each straight move agent -> agent + offset_k to the nearest valid obstacle.

    Parameters
    ----------
    rel_m : (A, M, D) obstacles relative to the agents (``near_obstacles``).
    valid : (A, M).
    offsets_m : (K, D) the moves (bacteria offsets), all of non-zero length.

    Returns
    -------
    (A, K) min over obstacles of the squared distance to the segment [0, offset_k] [m^2]; inf without obstacles.
    """
    n_agents, width, _ = rel_m.shape
    if width == 0:
        return np.full((n_agents, offsets_m.shape[0]), np.inf)
    axes = _axes(rel_m)
    return _segment_min(axes, _dot(axes, offsets_m), offsets_m, valid)


class MoveSweep:
    """The moves' swept clearance, the end points' distances and, optionally, probes from the end points, in one
    pass over the obstacles, with what depends only on the moves computed once (at one agent numpy's per-call
    cost dominates, so fewer and larger array operations are what makes a step fast).

    Every result equals, bit for bit, what ``segment_clearance_sq`` / ``segments_clearance_sq`` return: the same
    operations in the same order on the same values (tests/planning/test_planning_nav_digest.py pins it).

    Parameters
    ----------
    offsets_m : (K, D) the moves (bacteria offsets), all of non-zero length.
    """

    def __init__(self, offsets_m: FloatArray) -> None:
        n_points, dim = offsets_m.shape
        self.offsets_m = offsets_m
        self.o2 = np.einsum("kd,kd->k", offsets_m, offsets_m)
        # Moves (start 0, vector o_k) then probes (start o_k): the starts of the 2K segments, one array per axis.
        self._starts = [np.concatenate([np.zeros(n_points), offsets_m[:, d]]) for d in range(dim)]

    def __call__(
        self, rel_m: FloatArray, valid: BoolArray, r2_m2: FloatArray, probes_m: FloatArray | None
    ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """Sweep the moves (and probes) of A agents.

        Parameters
        ----------
        rel_m : (A, M, D) obstacles relative to the agents, M > 0; valid : (A, M).
        r2_m2 : (A, M) |rel|^2, the caller's.
        probes_m : (A, K, D) segments from the end point o_k along probes_m[a, k] (zero length: the point), or None.

        Returns
        -------
        (A, K) ``segment_clearance_sq`` of the moves; (M, A, K) squared distance from every obstacle to every end
        point, |rel|^2 - 2 rel.o + |o|^2 (>= 0; rows of padding obstacles hold meaningless values, the caller
        masks them); (A, K) ``segments_clearance_sq`` of the probes, or None.
        """
        offsets_m = self.offsets_m
        n_agents, width, dim = rel_m.shape
        n_points = offsets_m.shape[0]
        axes = _axes(rel_m)
        if probes_m is None:
            dot = _dot(axes, offsets_m)
            end2 = _end_sq(dot, self.o2, r2_m2)
            return _segment_min(axes, dot, offsets_m, valid), end2, None
        vectors = np.empty((n_agents, 2 * n_points, dim))
        vectors[:, :n_points] = offsets_m
        vectors[:, n_points:] = probes_m
        r2 = np.zeros((width, n_agents, 2 * n_points))
        dot = np.zeros((width, n_agents, 2 * n_points))
        for d in range(dim):
            rel = axes[d][:, :, None] - self._starts[d]  # (M, A, 2K): obstacle minus segment start
            r2 += rel * rel
            rel *= vectors[:, :, d]
            dot += rel
        end2 = _end_sq(dot[:, :, :n_points], self.o2, r2_m2)
        v2 = np.empty((n_agents, 2 * n_points))
        v2[:, :n_points] = self.o2
        v2[:, n_points:] = np.einsum("akd,akd->ak", probes_m, probes_m)
        # A zero-length probe has dot = 0: dividing by the smallest normal float gives t = 0 (its start point),
        # as segments_clearance_sq's NaN rule does, without a floating-point error state to switch off.
        np.maximum(v2, _TINY, out=v2)
        sweep_sq_inplace(dot, r2, v2)
        _invalid_to_inf(r2, valid)
        both = _clipped_min(r2)
        return both[:, :n_points], end2, both[:, n_points:]


def _end_sq(dot: FloatArray, o2: FloatArray, r2_m2: FloatArray) -> FloatArray:
    """(M, A, K) |rel - o_k|^2 = |rel|^2 - 2 rel.o_k + |o_k|^2 from the dot products rel.o_k (not consumed)."""
    end2 = dot * -2.0  # exact: scaling by 2 commutes with rounding, so this equals the sum of rel_d (-2 o_d)
    end2 += r2_m2.T[:, :, None]
    end2 += o2
    return np.maximum(end2, 0.0, out=end2)


def _dot(axes: list[FloatArray], offsets_m: FloatArray) -> FloatArray:
    """(M, A, K) rel . offset_k."""
    dot = axes[0][:, :, None] * offsets_m[:, 0]
    for d in range(1, len(axes)):
        dot += axes[d][:, :, None] * offsets_m[:, d]
    return dot


def _segment_min(axes: list[FloatArray], dot: FloatArray, offsets_m: FloatArray, valid: BoolArray) -> FloatArray:
    """(A, K) min over valid obstacles of the squared distance to the segments [0, offset_k]; ``dot`` is consumed."""
    o2 = np.einsum("kd,kd->k", offsets_m, offsets_m)
    r2 = axes[0] * axes[0]
    for d in range(1, len(axes)):
        r2 += axes[d] * axes[d]
    # A padding row (rel = 0, so dot = 0) starting from r2 = inf ends at inf - 0 = inf: the (M, A) plane is marked
    # instead of the (M, A, K) result.
    if not valid.all():
        np.copyto(r2, np.inf, where=~valid.T)
    # |rel - t o|^2 = r2 - t (2 dot - t o2), with the obstacles relative to the agent (no cancellation).
    d2 = np.empty_like(dot)
    d2[...] = r2[:, :, None]
    sweep_sq_inplace(dot, d2, o2)
    return _clipped_min(d2)


def segments_clearance_sq(
    rel_m: FloatArray, valid: BoolArray, starts_m: FloatArray, vectors_m: FloatArray
) -> FloatArray:
    """Like ``segment_clearance_sq`` for per-agent segments start_ak -> start_ak + vector_ak (relative to the agent).

    ``starts_m`` and ``vectors_m`` are (A, K, D); zero-length vectors are points. Returns (A, K) [m^2].
    """
    n_agents, width, dim = rel_m.shape
    n_seg = starts_m.shape[1]
    if width == 0:
        return np.full((n_agents, n_seg), np.inf)
    axes = _axes(rel_m)
    r2 = np.zeros((width, n_agents, n_seg))
    dot = np.zeros((width, n_agents, n_seg))
    for d in range(dim):
        rel = axes[d][:, :, None] - starts_m[:, :, d]  # (M, A, K): obstacle minus segment start
        r2 += rel * rel
        rel *= vectors_m[:, :, d]
        dot += rel
    v2 = np.einsum("akd,akd->ak", vectors_m, vectors_m)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = dot / v2
    t[~(t > 0.0)] = 0.0  # also NaN from a zero-length vector: the segment is its start point
    np.minimum(t, 1.0, out=t)
    dot *= 2.0
    dot -= t * v2
    dot *= t
    r2 -= dot
    _invalid_to_inf(r2, valid)
    return _clipped_min(r2)


def _clipped_min(d2: FloatArray) -> FloatArray:
    """(A, K) min over the obstacles of max(d2, 0) for (M, A, K) ``d2``, clipped after the reduction: max(., 0) is
    monotone, so the minimum of the clipped values is the clipped minimum, bit for bit (``d2`` is never NaN and
    never -0.0: it is |rel|^2 >= +0 minus a product, or +inf), at an (A, K) pass instead of an (M, A, K) one."""
    out = np.minimum.reduce(d2, axis=0)
    return np.asarray(np.maximum(out, 0.0, out=out), dtype=np.float64)


def sweep_sq_inplace(dot: FloatArray, r2: FloatArray, v2: FloatArray) -> None:
    """``r2`` becomes the squared distance from each obstacle to each segment (``dot`` is consumed):
    |rel - t v|^2 = |rel|^2 - t (2 rel.v - t |v|^2) with t = rel.v / |v|^2 clipped to [0, 1]. ``dot`` = rel.v,
    ``r2`` = |rel|^2, ``v2`` = |v|^2 (> 0), broadcast together. May round to a tiny negative value: callers clip."""
    sweep_term_inplace(dot, v2)
    r2 -= dot


def sweep_term_inplace(dot: FloatArray, v2: FloatArray) -> None:
    """``dot`` (rel.v) becomes t (2 rel.v - t |v|^2), what ``sweep_sq_inplace`` takes from |rel|^2."""
    t = dot / v2
    np.maximum(t, 0.0, out=t)
    np.minimum(t, 1.0, out=t)
    dot *= 2.0
    dot -= t * v2
    dot *= t
