"""Full-knowledge shortest path with a required clearance: the optimum beside each planner's mean path.

Method (2D, north/east metres):

1. Grid: nodes every ``resolution_m`` over the bounding box of start, goal and obstacles (padded by the
   clearance + 2 m, so a way around the outside counts). A node is free when its exact distance to every TRUE
   obstacle surface (cylinder of its radius, wall capsule of half its thickness) is >= ``clearance_m``.
2. Search: Dijkstra (``scipy.sparse.csgraph.dijkstra``, compiled) on the 16-connected grid (moves (1,0), (1,1),
   (2,1) and their symmetries; a move needs the cells it cuts across free too). 16-connected grid paths are at
   most 2.7 % longer than the straight line between their ends (8-connected: 8.2 %).
3. Any-angle refinement, every segment checked exactly against the true geometry (segment/obstacle distances
   >= ``clearance_m``): greedy string pulling (from each anchor to the farthest later vertex in view), then a
   relaxation that slides each bend towards its neighbours or onto the line between them while both new
   segments stay clear (the path only shortens), once more after adding a vertex in every segment, and a last
   string pulling. The start and goal join the grid at their nearest free nodes.

A world's flying area and keep-out zones (a user's fence) bound the way too: their edges are added as walls of no
thickness (``_with_zone_walls``), so the path keeps ``clearance_m`` from them as from any wall and never leaves the
area or enters a zone.

The result is a feasible path (every bundled world's path keeps the clearance on every segment: tested; only a
start or goal that itself lies closer, or a grid edge no refinement replaced, may not): an upper bound on the
true optimum, tight up to how well a few straight bends
follow an arc where the path wraps an obstacle. Measured (``tests/sim/study/test_optimal.py`` and the docs): a detour
round one disc +0.03 % at 0.1 m and 0.2 m grids, a 53-degree wrap of a 1.35 m disc +0.3 %; straight lines are
exact; on 30 random reference fields the 0.2 m grid gives on average 0.14 % (at most 0.7 %) more than 0.1 m.
A gap narrower than the grid resolves (within ~``resolution_m`` of 2 * clearance) may be missed, making the
optimum a little longer there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from apf_companion.planning import area_polygon
from sim.world.geometry import clearance_many_m, segment_clearance_m
from sim.world.model import FloatArray, World

__all__ = [
    "DEFAULT_CLEARANCE_M",
    "DEFAULT_RESOLUTION_M",
    "FIELD_RESOLUTION_M",
    "OptimalPath",
    "optimal_path",
    "optimal_path_points",
]

DEFAULT_CLEARANCE_M = 0.35
"""The study's collision radius 0.25 m plus a 0.1 m margin."""
DEFAULT_RESOLUTION_M = 0.1
FIELD_RESOLUTION_M = 0.2
"""The random fields' default (many fields; 2-3x faster, on average 0.14 % longer than at 0.1 m)."""

# 16-connected moves (one of each +/- pair) and the cells each one cuts across (must be free too).
_MOVES: tuple[tuple[int, int, tuple[tuple[int, int], ...]], ...] = (
    (1, 0, ()),
    (0, 1, ()),
    (1, 1, ((1, 0), (0, 1))),
    (1, -1, ((1, 0), (0, -1))),
    (2, 1, ((1, 0), (1, 1))),
    (1, 2, ((0, 1), (1, 1))),
    (2, -1, ((1, 0), (1, -1))),
    (1, -2, ((0, -1), (1, -1))),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class OptimalPath:
    """The full-knowledge optimum of one start/goal pair."""

    length_m: float
    """Length of the refined path [m]; inf when no path keeps the clearance."""
    grid_length_m: float
    """Length of the 16-connected grid path before refinement [m] (inf when none)."""
    path_ne_m: FloatArray
    """(K, 2) vertices of the refined path, start to goal (empty when none)."""
    clearance_m: float
    resolution_m: float


def optimal_path(
    world: World,
    start_ne_m: Sequence[float] | None = None,
    goal_ne_m: Sequence[float] | None = None,
    *,
    clearance_m: float = DEFAULT_CLEARANCE_M,
    resolution_m: float = DEFAULT_RESOLUTION_M,
) -> OptimalPath:
    """The shortest path that keeps ``clearance_m`` from ``world``'s true obstacles (see the module doc).

    ``start_ne_m``/``goal_ne_m`` default to the world's own.
    """
    start = _endpoint(start_ne_m, world.start_ne_m, "start")
    goal = _endpoint(goal_ne_m, world.goal_ne_m, "goal")
    world = _with_zone_walls(world)
    if not (math.isfinite(clearance_m) and clearance_m >= 0 and math.isfinite(resolution_m) and resolution_m > 0):
        msg = f"optimal_path: need clearance >= 0 and resolution > 0, got {clearance_m!r}, {resolution_m!r}"
        raise ValueError(msg)
    nodes_n, nodes_e, free = _grid(world, start, goal, clearance_m, resolution_m)
    h = resolution_m
    shape = free.shape

    def node(p: FloatArray) -> int:
        # The nearest free node (the endpoints themselves may sit closer than the clearance to an obstacle).
        i = np.clip(np.rint((p[0] - nodes_n[0]) / h), 0, shape[0] - 1)
        j = np.clip(np.rint((p[1] - nodes_e[0]) / h), 0, shape[1] - 1)
        fi, fj = np.nonzero(free)
        if fi.size == 0:
            return -1
        k = int(np.argmin((fi - i) ** 2 + (fj - j) ** 2))
        return int(fi[k] * shape[1] + fj[k])

    s_idx, g_idx = node(start), node(goal)
    none = OptimalPath(
        length_m=math.inf,
        grid_length_m=math.inf,
        path_ne_m=np.zeros((0, 2)),
        clearance_m=clearance_m,
        resolution_m=resolution_m,
    )
    if s_idx < 0 or g_idx < 0:
        return none
    idx = _grid_path(free, h, s_idx, g_idx)
    if idx is None:
        return none
    ii, jj = np.divmod(idx, shape[1])
    grid_pts = np.stack([nodes_n[ii], nodes_e[jj]], axis=1)
    pts = np.concatenate([start[None], grid_pts, goal[None]])
    grid_len = _length(pts)
    refined = _relax(world, _pull_string(world, pts, clearance_m), clearance_m)
    # Wrapping an obstacle takes more than one bend: add a vertex in every segment and relax again.
    refined = _relax(world, _subdivide(refined), clearance_m)
    refined = _pull_string(world, refined, clearance_m)
    return OptimalPath(
        length_m=_length(refined),
        grid_length_m=grid_len,
        path_ne_m=refined,
        clearance_m=clearance_m,
        resolution_m=resolution_m,
    )


def optimal_path_points(
    points_ne_m: npt.ArrayLike,
    start_ne_m: Sequence[float],
    goal_ne_m: Sequence[float],
    *,
    clearance_m: float = DEFAULT_CLEARANCE_M,
    resolution_m: float = DEFAULT_RESOLUTION_M,
) -> OptimalPath:
    """The optimum among point obstacles (the paper's random fields: cylinders of radius 0)."""
    pts = np.asarray(points_ne_m, dtype=np.float64).reshape(-1, 2)
    world = World.from_obstacles(pts, 0.0, name="field")
    return optimal_path(world, start_ne_m, goal_ne_m, clearance_m=clearance_m, resolution_m=resolution_m)


def _with_zone_walls(world: World) -> World:
    """``world`` with the edges of its flying area and keep-out zones as walls of no thickness (module docstring)."""
    zones = [*([] if world.area_ne_m is None else [area_polygon(world.area_ne_m)]), *world.keepouts_ne_m]
    if not zones:
        return world
    segs = np.concatenate([World.polygon_segments(zone) for zone in zones])
    edges = World(walls_ne_m=segs, wall_thickness_m=np.zeros(len(segs)), wall_heights_m=np.full(len(segs), np.inf))
    return world.merged(edges, name=world.name)


def _endpoint(given: Sequence[float] | None, default: tuple[float, float] | None, what: str) -> FloatArray:
    value = given if given is not None else default
    if value is None:
        msg = f"optimal_path: no {what} given and the world has none"
        raise ValueError(msg)
    return np.asarray(value, dtype=np.float64).reshape(2)


def _grid(
    world: World, start: FloatArray, goal: FloatArray, clearance_m: float, h: float
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """Node coordinates along north and east, and the (H, W) free mask."""
    corners = [start[None], goal[None], world.circles_ne_m, world.walls_ne_m.reshape(-1, 2)]
    allpts = np.concatenate(corners)
    pad = clearance_m + 2.0 + float(np.max(world.circle_radii_m, initial=0.0))
    lo = np.floor((allpts.min(axis=0) - pad) / h) * h
    hi = allpts.max(axis=0) + pad
    nodes_n = lo[0] + h * np.arange(int(np.ceil((hi[0] - lo[0]) / h)) + 1)
    nodes_e = lo[1] + h * np.arange(int(np.ceil((hi[1] - lo[1]) / h)) + 1)
    free = np.ones((nodes_n.size, nodes_e.size), dtype=bool)
    _block_circles(free, nodes_n, nodes_e, world, clearance_m, h)
    if world.n_walls:
        walls = World(
            walls_ne_m=world.walls_ne_m, wall_thickness_m=world.wall_thickness_m, wall_heights_m=world.wall_heights_m
        )
        # Row blocks keep the (cells x walls) distance arrays small.
        block = max(1, 2_000_000 // max(1, nodes_e.size * walls.n_walls))
        for r0 in range(0, nodes_n.size, block):
            nn, ee = np.meshgrid(nodes_n[r0 : r0 + block], nodes_e, indexing="ij")
            d = clearance_many_m(walls, np.stack([nn.ravel(), ee.ravel()], axis=1))
            free[r0 : r0 + block] &= (d >= clearance_m).reshape(nn.shape)
    return nodes_n, nodes_e, free


def _block_circles(
    free: npt.NDArray[np.bool_], nodes_n: FloatArray, nodes_e: FloatArray, world: World, clearance_m: float, h: float
) -> None:
    """Mark the nodes closer than ``clearance_m`` to a cylinder as blocked: one stencil of node offsets around
    every centre at once (exact squared-distance test on each node; no per-obstacle loop)."""
    if world.n_circles == 0:
        return
    reach = float(world.circle_radii_m.max()) + clearance_m
    k = math.ceil(reach / h) + 1
    off = np.arange(-k, k + 1)
    ci = np.rint((world.circles_ne_m[:, 0] - nodes_n[0]) / h).astype(np.intp)
    cj = np.rint((world.circles_ne_m[:, 1] - nodes_e[0]) / h).astype(np.intp)
    ii, jj = np.broadcast_arrays(ci[:, None, None] + off[None, :, None], cj[:, None, None] + off[None, None, :])
    inside = (ii >= 0) & (ii < nodes_n.size) & (jj >= 0) & (jj < nodes_e.size)
    ii, jj = np.clip(ii, 0, nodes_n.size - 1), np.clip(jj, 0, nodes_e.size - 1)
    dn = nodes_n[ii] - world.circles_ne_m[:, 0, None, None]
    de = nodes_e[jj] - world.circles_ne_m[:, 1, None, None]
    limit = (world.circle_radii_m + clearance_m)[:, None, None]
    blocked = inside & (dn * dn + de * de < limit * limit)
    free[ii[blocked], jj[blocked]] = False


def _grid_path(free: npt.NDArray[np.bool_], h: float, s_idx: int, g_idx: int) -> npt.NDArray[np.intp] | None:
    """Node indices of the shortest 16-connected path from s_idx to g_idx, or None."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    rows, cols = free.shape
    ii, jj = np.nonzero(free)
    src: list[npt.NDArray[np.intp]] = []
    dst: list[npt.NDArray[np.intp]] = []
    wts: list[FloatArray] = []
    for di, dj, via in _MOVES:
        ti, tj = ii + di, jj + dj
        ok = (ti >= 0) & (ti < rows) & (tj >= 0) & (tj < cols)
        ok[ok] = free[ti[ok], tj[ok]]
        for vi, vj in via:
            ui, uj = ii + vi, jj + vj
            inside = (ui >= 0) & (ui < rows) & (uj >= 0) & (uj < cols)
            ok &= inside
            ok[ok] = free[ui[ok], uj[ok]]
        src.append(ii[ok] * cols + jj[ok])
        dst.append(ti[ok] * cols + tj[ok])
        wts.append(np.full(int(ok.sum()), h * math.hypot(di, dj)))
    n = rows * cols
    graph = coo_matrix((np.concatenate(wts), (np.concatenate(src), np.concatenate(dst))), shape=(n, n)).tocsr()
    dist, pred = dijkstra(graph, directed=False, indices=s_idx, return_predecessors=True)
    if not math.isfinite(float(dist[g_idx])):
        return None
    out = [g_idx]
    while out[-1] != s_idx:
        out.append(int(pred[out[-1]]))
    return np.asarray(out[::-1], dtype=np.intp)


def _pull_string(world: World, pts: FloatArray, clearance_m: float) -> FloatArray:
    """Greedy farthest-visible shortcutting of a polyline against the true geometry."""
    keep = [0]
    i = 0
    last = pts.shape[0] - 1
    while i < last:
        later = np.arange(i + 1, last + 1)
        ok = segment_clearance_m(world, np.broadcast_to(pts[i], (later.size, 2)), pts[later]) >= clearance_m - 1e-9
        visible = later[ok]
        i = int(visible.max()) if visible.size else i + 1
        keep.append(i)
    return np.asarray(pts[keep], dtype=np.float64)


_RELAX_STEPS = tuple(2.0**-k for k in (0, 1, 2, 3, 4, 6, 8, 10))


def _relax(world: World, pts: FloatArray, clearance_m: float, rounds: int = 60) -> FloatArray:
    """Pull the path taut: move each interior vertex b (neighbours a, c) towards a, towards c or towards its
    projection onto a-c, by the step of ``_RELAX_STEPS`` (fractions of the way) that shortens a-b-c most while
    keeping both new segments clear; even and odd vertices in turn.

    Each such move never lengthens a-b-c (triangle inequality; |ab'| + |b'c| is convex along the way to the
    projection and least on a-c), so the path only shortens, and every accepted segment is checked exactly.
    """
    p = pts.copy()
    n = p.shape[0]
    if n < 3:
        return p
    steps = np.asarray(_RELAX_STEPS)
    for _ in range(rounds):
        gained = 0.0
        for parity in (1, 2):
            idx = np.arange(parity, n - 1, 2)
            if idx.size == 0:
                continue
            a, b, c = p[idx - 1], p[idx], p[idx + 1]
            ac = c - a
            denom = np.maximum(np.sum(ac * ac, axis=1), 1e-18)
            t = np.clip(np.sum((b - a) * ac, axis=1) / denom, 0.0, 1.0)
            proj = a + t[:, None] * ac
            aims = np.stack([a, c, proj])  # (3, I, 2)
            cand = b[None, None] + steps[None, :, None, None] * (aims - b[None])[:, None]  # (3, S, I, 2)
            flat = cand.reshape(-1, 2)
            aa = np.broadcast_to(a, cand.shape).reshape(-1, 2)
            cc = np.broadcast_to(c, cand.shape).reshape(-1, 2)
            # Both new segments in one call (a -> b' and b' -> c): the cost here is per numpy call, not per pair.
            both = segment_clearance_m(world, np.concatenate([aa, flat]), np.concatenate([flat, cc])) >= clearance_m
            ok = both[: flat.shape[0]] & both[flat.shape[0] :]
            cost = np.where(ok, np.hypot(*(flat - aa).T) + np.hypot(*(cc - flat).T), np.inf).reshape(-1, idx.size)
            best = np.argmin(cost, axis=0)
            now = np.hypot(*(b - a).T) + np.hypot(*(c - b).T)
            better = cost[best, np.arange(idx.size)] < now - 1e-12
            new_b = np.where(better[:, None], cand.reshape(-1, idx.size, 2)[best, np.arange(idx.size)], b)
            gained += float(np.sum(np.where(better, now - cost[best, np.arange(idx.size)], 0.0)))
            p[idx] = new_b
        if gained < 1e-4:  # 0.1 mm per round
            break
    return p


def _subdivide(pts: FloatArray) -> FloatArray:
    """The polyline with the midpoint of every segment inserted."""
    mid = 0.5 * (pts[:-1] + pts[1:])
    out = np.empty((2 * pts.shape[0] - 1, 2))
    out[0::2] = pts
    out[1::2] = mid
    return out


def _length(pts: FloatArray) -> float:
    if pts.shape[0] < 2:
        return 0.0
    d = np.diff(pts, axis=0)
    return float(np.hypot(d[:, 0], d[:, 1]).sum())
