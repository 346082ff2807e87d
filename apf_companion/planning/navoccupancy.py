"""Occupancy of bapf-nav's navigation grid (``navfield``): the cells that obstacle points block.

A cell is blocked when its centre is closer than the planner's clearance to a remembered obstacle point (the
obstacles inflated by the clearance). Each point marks a small stencil of cells around its own, vectorised over all
points of all agents at once.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ["stencil_blocked"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
_all = np.logical_and.reduce


def stencil_blocked(
    n: int,
    cell_m: float,
    origins_m: FloatArray,
    obstacles_xy_m: FloatArray,
    valid: BoolArray,
    radii_m: tuple[float, ...],
) -> list[BoolArray]:
    """(B, n^2) cells of grids of ``n`` x ``n`` cells of ``cell_m`` (lower corners ``origins_m`` (B, 2)) whose centre
    lies closer than each of ``radii_m`` to a valid obstacle point (``obstacles_xy_m`` (B, N, 2), ``valid`` (B, N)):
    one stencil, the largest radius's, marks the same cells for each."""
    h = cell_m
    outs = [np.zeros((origins_m.shape[0], n * n), dtype=bool) for _ in radii_m]
    if obstacles_xy_m.shape[1] == 0 or not valid.any():
        return outs
    top = max(radii_m)
    # Stencil offsets s from each point's cell: a cell's centre is more than (|s| - 0.5) h away, so cells
    # with |s| >= top / h + 0.5 are never within ``top``; one more cell each way keeps rounding far off.
    half = math.ceil(top / h + 0.5)
    steps = np.arange(-half, half + 1)
    s = steps.size
    b, m = np.nonzero(valid)
    rel = (obstacles_xy_m[b, m] - origins_m[b]) / h  # (P, 2) in cells
    base = np.floor(rel).astype(np.intp)
    # Points whose whole stencil lies off the grid mark nothing: leave them out (the memory of a flight
    # reaches far beyond the grid around the agent).
    reach = _all((base >= -half) & (base < n + half), axis=1)
    if not _all(reach, axis=None):
        b, rel, base = b[reach], rel[reach], base[reach]
    ci = base[:, 0:1] + steps[None, :]  # (P, S) stencil rows
    cj = base[:, 1:2] + steps[None, :]  # (P, S) stencil columns
    ddx = (ci + 0.5 - rel[:, 0:1]) * h
    ddy = (cj + 0.5 - rel[:, 1:2]) * h
    # The stencil is separable: (P, S, S) squared distances from one row and one column term per point; rows
    # and columns outside the grid are at infinity.
    dx2 = np.where((ci >= 0) & (ci < n), ddx * ddx, np.inf)
    dy2 = np.where((cj >= 0) & (cj < n), ddy * ddy, np.inf)
    d2 = (dx2[:, :, None] + dy2[:, None, :]).ravel()
    # The cells of the largest radius (the others are among them), as flat indices into (P, S, S): one index
    # array and 1-D gathers instead of three.
    k = np.flatnonzero(d2 < top * top)
    near2 = d2[k]
    point_row, col = np.divmod(k, s)  # point * S + stencil row, stencil column
    point = point_row // s
    rows, cells = b[point], ci.ravel()[point_row] * n + cj.ravel()[point * s + col]
    for out, radius in zip(outs, radii_m, strict=True):
        if radius == top:  # every cell found
            out[rows, cells] = True
        else:
            hit = near2 < radius * radius
            out[rows[hit], cells[hit]] = True
    return outs
