"""bapf-nav's line-of-sight test over a batch of agents (``EscapeMaps.sight_blocked`` has the rule).

Two stages per group of agents: which known points lie within the clearance C of each agent's line (every point
of every looking agent), then, for the agents with such hits, whether one of the first ``SIGHT_FIRST`` hits along
the line is part of a surface (two other known points within ``SURFACE_M``). The second stage compares each pick
only with the points within C + ``SURFACE_M`` (+ ``_AROUND_SLACK_M``) of the line, as the single-agent test does
(``navsingle.SightLine``): a neighbour of a pick is within ``SURFACE_M`` of a point within C of the line, so within
C + ``SURFACE_M`` of it (the distance to a segment changes by at most the distance moved). Differences of floats
are exact to a relative 2^-53 of the difference, whatever the coordinates' size, so the rounding of those
distances (a few metres) is far below the slack. In a crowded study field nearly every looking agent has a hit,
and the points near its line are a few of the ~100 it knows: the second stage was two thirds of the test.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apf_companion.planning.clearance import compact_rows

__all__ = ["SIGHT_FIRST", "SURFACE_M", "sight_blocked"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]

#: Agents x obstacle points per group in the first stage.
_SIGHT_CELLS = 32768
#: Known points closer than this to each other belong to one surface (sampled every 0.2 m).
SURFACE_M = 0.45
#: Blocking points tested for being part of a surface, the first along the line.
SIGHT_FIRST = 3
#: Slack of the neighbour prefilter [m]: the rounding of the distances it compares is below 1e-12 m.
_AROUND_SLACK_M = 1e-3
#: Smallest normal float64: the divisor for an agent on its goal (zero direction, never 0/0).
_TINY = float(np.finfo(np.float64).tiny)
_sum = np.add.reduce
_any = np.logical_or.reduce


def sight_blocked(
    active: BoolArray,
    positions_m: FloatArray,
    targets_m: FloatArray,
    obstacles_m: FloatArray,
    obstacle_mask: BoolArray | None,
    reach_m: tuple[float, float, float],
) -> BoolArray:
    """(A,) agents of ``active`` whose line to the goal is blocked by a surface; ``reach_m`` = (sight, step, C)."""
    sight_m = reach_m[0]
    out = np.zeros(positions_m.shape[0], dtype=bool)
    if sight_m <= 0.0 or obstacles_m.shape[1] == 0:
        return out
    rows = np.flatnonzero(active)
    group = max(1, _SIGHT_CELLS // obstacles_m.shape[1])  # (group, M) temporaries stay small
    for lo in range(0, rows.size, group):
        r = rows[lo : lo + group]
        mask = None if obstacle_mask is None else obstacle_mask[r]
        out[r] = _group(positions_m[r], targets_m[r], obstacles_m[r], mask, reach_m)
    return out


def _group(
    positions_m: FloatArray,
    targets_m: FloatArray,
    obs: FloatArray,
    mask: BoolArray | None,
    reach_m: tuple[float, float, float],
) -> BoolArray:
    """``sight_blocked`` of one group of agents (all looking)."""
    sight_m, step_m, clearance_m = reach_m
    to_goal = targets_m - positions_m
    dist = np.sqrt(np.einsum("ad,ad->a", to_goal, to_goal))
    unit = to_goal / np.maximum(dist, _TINY)[:, None]
    end = np.minimum(dist, sight_m)
    start = np.minimum(step_m, end)
    with np.errstate(invalid="ignore", over="ignore"):  # unknown rows may be non-finite: they compare False
        along, off2 = _line_offsets(obs, positions_m, unit, start, end)
    hit = off2 < clearance_m * clearance_m
    if mask is not None:
        hit &= mask
    out = np.zeros(positions_m.shape[0], dtype=bool)
    some = np.flatnonzero(_any(hit, axis=1))
    if some.size == 0:
        return out
    first = min(SIGHT_FIRST, obs.shape[1])
    order = np.where(hit[some], along[some], np.inf)
    picks = np.argpartition(order, first - 1, axis=1)[:, :first]  # (S, F) the first hits along the line
    real = np.take_along_axis(hit[some], picks, axis=1)
    pts = obs[some[:, None], picks]  # (S, F, D)
    around = off2[some] < (clearance_m + SURFACE_M + _AROUND_SLACK_M) ** 2  # NaN compares False
    if mask is not None:
        around &= mask[some]
    near, valid = compact_rows(obs[some], around)  # (S, W, D): the picks' possible neighbours
    with np.errstate(invalid="ignore", over="ignore"):
        gap = near[:, None, :, :] - pts[:, :, None, :]  # (S, F, W, D)
        d2 = np.einsum("sfmd,sfmd->sfm", gap, gap)
    close = (d2 < SURFACE_M * SURFACE_M) & (d2 > 0.0) & valid[:, None, :]
    out[some] = _any((_sum(close, axis=2) >= 2) & real, axis=1)
    return out


def _line_offsets(
    obs: FloatArray, positions_m: FloatArray, unit: FloatArray, start: FloatArray, end: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(G, M) each: how far along each agent's line its points lie, and their squared distance to the segment
    [start, end] of it. 2D on the two coordinate planes, the sums of two products written out (einsum's sums bit
    for bit: one rounding, in either order; einsum over the short coordinate axis costs several times more);
    3D keeps einsum and its order."""
    if obs.shape[2] != 2:
        rel = obs - positions_m[:, None, :]
        along = np.einsum("amd,ad->am", rel, unit)
        t = np.clip(along, start[:, None], end[:, None])
        off = rel - t[:, :, None] * unit[:, None, :]
        return along, np.einsum("amd,amd->am", off, off)
    rel_n = obs[:, :, 0] - positions_m[:, 0, None]
    rel_e = obs[:, :, 1] - positions_m[:, 1, None]
    u_n, u_e = unit[:, 0, None], unit[:, 1, None]
    along = rel_n * u_n
    along += rel_e * u_e
    t = np.clip(along, start[:, None], end[:, None])
    rel_n -= t * u_n
    rel_e -= t * u_e
    rel_n *= rel_n
    rel_e *= rel_e
    rel_n += rel_e
    return along, rel_n
