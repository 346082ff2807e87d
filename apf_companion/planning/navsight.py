"""bapf-nav's line-of-sight test over a batch of agents (``EscapeMaps.sight_blocked`` has the rule): is any known
point within the clearance C of each looking agent's line?

Agents go in groups of about ``_SIGHT_CELLS`` agent-point pairs. 2D runs on the coordinate planes with the sums of
two products written out: einsum's sums bit for bit (a sum of two terms has one rounding, in either order), and
einsum over the short coordinate axis costs several times more. 3D keeps einsum and its order (the single-agent
test, ``navsingle.SightLine``, uses the same einsum).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["sight_blocked"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Agents x obstacle points per group.
_SIGHT_CELLS = 32768
#: Smallest normal float64: the divisor for an agent on its goal (zero direction, never 0/0).
_TINY = float(np.finfo(np.float64).tiny)
_any = np.logical_or.reduce


def sight_blocked(
    active: BoolArray,
    positions_m: FloatArray,
    targets_m: FloatArray,
    obstacles_m: FloatArray,
    obstacle_mask: BoolArray | None,
    reach_m: tuple[float, float, float],
) -> BoolArray:
    """(A,) agents of ``active`` with a known point within C of the line to the goal; ``reach_m`` = (sight, step,
    C) [m]: the line runs from min(step, end) to end = min(distance to the goal, sight)."""
    sight_m, step_m, clearance_m = reach_m
    out = np.zeros(positions_m.shape[0], dtype=bool)
    if sight_m <= 0.0 or obstacles_m.shape[1] == 0:
        return out
    rows = np.flatnonzero(active)
    group = max(1, _SIGHT_CELLS // obstacles_m.shape[1])  # (group, M) temporaries stay small
    for lo in range(0, rows.size, group):
        r = rows[lo : lo + group]
        to_goal = targets_m[r] - positions_m[r]
        dist = np.sqrt(np.einsum("ad,ad->a", to_goal, to_goal))
        unit = to_goal / np.maximum(dist, _TINY)[:, None]
        end = np.minimum(dist, sight_m)
        start = np.minimum(step_m, end)
        with np.errstate(invalid="ignore", over="ignore"):  # unknown rows may be non-finite: they compare False
            hit = _line_offsets_sq(obstacles_m[r], positions_m[r], unit, start, end) < clearance_m * clearance_m
        if obstacle_mask is not None:
            hit &= obstacle_mask[r]
        out[r] = _any(hit, axis=1)
    return out


def _line_offsets_sq(
    obs: FloatArray, positions_m: FloatArray, unit: FloatArray, start: FloatArray, end: FloatArray
) -> FloatArray:
    """(G, M) squared distance of each agent's points (G, M, D) to the segment [start, end] of its line."""
    if obs.shape[2] != 2:
        rel = obs - positions_m[:, None, :]
        along = np.einsum("amd,ad->am", rel, unit)
        t = np.clip(along, start[:, None], end[:, None])
        off = rel - t[:, :, None] * unit[:, None, :]
        return np.asarray(np.einsum("amd,amd->am", off, off), dtype=np.float64)
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
    return rel_n
