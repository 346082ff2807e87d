"""bapf-nav's escape maps: per agent, the navigation potential of the remembered obstacles (``navfield``).

Owns the grid geometry and the rules of when a potential is (re)computed: on entering ESCAPE without one, when
it is ``nav_replan_steps`` steps old, when a newly seen obstacle lies near its shortest way (``outdated``), when
the descent stalls, and after marking refused downhill cells as virtual obstacles (the grid let the potential
through a gap that the swept test refuses). The line of sight that starts an escape early is ``navsight``.
Blocked cells are remembered across recomputations and carried over when the grid moves; edge cells near the
agent's trail are not taken as exits (``_distances``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from apf_companion.planning.navfield import NavGrid
from apf_companion.planning.navstate import GiveUp, NavField, NavMode, NavState
from apf_companion.planning.params import PlannerParams

__all__ = ["AgentRows", "EscapeMaps", "mark_dead_end", "own_cell_blocked"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]

#: A field is tested against newly seen obstacles (``EscapeMaps.outdated``) once it is this many steps old: a
#: bound on the fields an agent can cost while its map grows (one every few moves, not one per move).
_OUTDATED_AGE = 8
_any = np.logical_or.reduce
_GAVE_UP = np.int8(NavMode.GAVE_UP)
#: Fields an agent's memo keeps (``NavField.memo``): the closed and the open field of one input. Over 300 study
#: trials at 70-95 one or four reuse as many fields as two; the memory is the agent's, 23 kB a field at 54 x 54.
_MEMO = 2
#: Slack of the seen-edge prefilter (``seen_edge_cells``) [m]: far above the rounding of coordinates of a flight.
_SEEN_SLACK_M = 1e-3


class AgentRows(NamedTuple):
    """What the escape rules read of a batch of agents (all rows; ``rows`` arguments pick from them)."""

    positions_m: FloatArray
    targets_m: FloatArray
    obstacles_m: FloatArray
    obstacle_mask: BoolArray | None
    state: NavState


class EscapeMaps:
    """The escape potentials of a planner's agents (their ``NavField`` lives in ``NavState.field``)."""

    def __init__(self, params: PlannerParams, offsets_m: FloatArray, clearance_m: float) -> None:
        self.params = params
        # The zones' edges are kept at C, as obstacles are (``navzones``).
        self.grid = NavGrid(
            params.nav_cell_m, params.nav_grid_m, params.nav_area_ne_m, params.nav_keepout_ne_m, clearance_m
        )
        self.clearance_m = clearance_m
        self._offsets = offsets_m
        self._pad_m = 2.0 * params.step_m + clearance_m + 1.0
        #: A refresh keeps the old grid while the agent is this far inside every side. Farther than the edge cells
        #: that its trail closes as seen (``nav_seen_m``): otherwise an agent that walks towards a side closes that
        #: side's exits before the grid moves on, and what it saw beyond the side (a gap just outside the grid)
        #: never enters a field. Seen in `apf-sim fly --world wall-gap`: the agent paced the wall between two
        #: closed sides for 120 s, 1.5 m short of the gap.
        self._keep_m = max(self._pad_m, params.nav_seen_m + 1.0)
        #: Around a point known now, remembered obstacle cells give way to the points' own inflation: C plus a
        #: cell's diagonal (a point that moved by range noise re-inflates the cells it blocked before).
        self._reach_m = clearance_m + params.nav_cell_m * 2.0**0.5
        #: The inflation of a field computed again for an agent that its field closes in (``refresh``): C less
        #: half a cell. Cells are blocked by their centre, so at C a gap of width w >= 2 C opens only where the
        #: lattice puts a centre in the w - 2 C between its inflated sides; at C - h / 2 that interval is at
        #: least a cell wide, so every gap the vehicle passes opens, and none narrower than 2 C - h.
        self.loose_m = max(clearance_m - 0.5 * params.nav_cell_m, 0.0)
        self._edge_cells = self.grid.edge_cells
        self._edge_centres = self.grid.edge_centres_m  # relative to the grid's corner

    def potentials(
        self,
        rows: IntArray,
        agents: AgentRows,
        feasible: BoolArray,
        clear_k: FloatArray,
        clear_0: FloatArray,
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Geodesic potential at the points (R, K) and the agents (R,) of ``rows``, and which points pass
        (feasible and lower on potential + clearance term), recomputing stale potentials."""
        positions_m, targets_m, obstacles_m, obstacle_mask, state = agents
        stale = np.array([state.field[r] is None for r in rows], dtype=bool)
        stale |= state.since_field[rows] >= self.params.nav_replan_steps
        check = ~stale & (state.since_field[rows] >= _OUTDATED_AGE)
        stale[check] = self.outdated(rows[check], positions_m, obstacles_m, obstacle_mask, state)
        if stale.any():
            self.refresh(rows[stale], positions_m, targets_m, obstacles_m, obstacle_mask, state)
        g_k, g0 = self.geodesic(rows, positions_m, targets_m, state)
        ok: BoolArray = np.asarray(feasible[rows] & (g_k + clear_k[rows] < (g0 + clear_0[rows])[:, None]))
        # Stalled on a potential that may be stale: recompute once with what is known now.
        stalled = ~ok.any(axis=1) & ~stale
        if stalled.any():
            again = rows[stalled]
            self.refresh(again, positions_m, targets_m, obstacles_m, obstacle_mask, state)
            g_k[stalled], g0[stalled] = self.geodesic(again, positions_m, targets_m, state)
            ok[stalled] = feasible[again] & (g_k[stalled] + clear_k[again] < (g0[stalled] + clear_0[again])[:, None])
        # Still nothing: the grid lets the potential through a gap the sweep refuses (a diagonal between two
        # free cells can cut an inflated obstacle). Mark the cells of the refused points that lead downhill as
        # blocked (virtual obstacles, kept with the remembered cells) and recompute once.
        # A dead row was refreshed above (it was stale or stalled): where no new cell was marked, a refresh would
        # give that same field again (same points, position, trail, frame and cells), so it is skipped.
        dead = np.flatnonzero(~ok.any(axis=1))
        if dead.size:
            dead = dead[self.mark_dead_ends(rows[dead], positions_m, feasible[rows[dead]], g_k[dead], g0[dead], state)]
        if dead.size:
            again = rows[dead]
            self.refresh(again, positions_m, targets_m, obstacles_m, obstacle_mask, state)
            g_k[dead], g0[dead] = self.geodesic(again, positions_m, targets_m, state)
            ok[dead] = feasible[again] & (g_k[dead] + clear_k[again] < (g0[dead] + clear_0[again])[:, None])
        return g_k, g0, ok

    def scores(
        self,
        rows: IntArray,
        agents: AgentRows,
        feasible: BoolArray,
        clear_k: FloatArray,
        clear_0: FloatArray,
        cost: FloatArray,
        cost0: FloatArray,
        passing: BoolArray,
    ) -> None:
        """Replace the escaping ``rows``' scores by the geodesic ones (in place; ``BapfNavPlanner._decide``'s
        ``cost``, ``cost0`` and ``passing``), and give up the rows whose region has no way (``GiveUp.NO_WAY``)."""
        positions_m, state = agents.positions_m, agents.state
        g_k, g0, ok = self.potentials(rows, agents, feasible, clear_k, clear_0)
        # Any feasible point down the potential (the clearance term may hold the agent on a plateau).
        plain: BoolArray = np.asarray(feasible[rows] & (g_k < g0[:, None]))
        has_ok = np.asarray(ok.any(axis=1))
        ok = np.asarray(np.where(has_ok[:, None], ok, plain), dtype=np.bool_)
        cost[rows] = g_k + clear_k[rows]
        cost0[rows] = np.where(np.asarray(ok.any(axis=1)), g0 + clear_0[rows], np.inf)
        # Every feasible point is off the map's free cells: inside the inflated obstacles (noise put the agent
        # there: no value at it and its own cell blocked), the agent first backs out (least clearance term); from
        # a free cell it is "no path" (its region is closed, even at C - h / 2): give up.
        lost = feasible[rows].any(axis=1) & ~np.isfinite(np.where(feasible[rows], g_k, np.inf)).any(axis=1)
        inside = lost & ~np.isfinite(g0)
        for i in np.flatnonzero(inside):  # no value at the agent: inside only where its own cell is blocked
            inside[i] = own_cell_blocked(self.grid, state.field[rows[i]], positions_m[rows[i], :2])
        ok[inside] = feasible[rows[inside]]
        cost[rows[inside]] = clear_k[rows[inside]]
        cost0[rows[inside]] = np.inf
        passing[rows] = ok
        state.mode[rows[lost & ~inside]] = _GAVE_UP
        state.gave_up[rows[lost & ~inside]] = GiveUp.NO_WAY

    def outdated(
        self,
        rows: IntArray,
        positions_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: NavState,
    ) -> BoolArray:
        """(R,) fields of ``rows`` that a newly seen obstacle makes wrong where it matters: a known point within
        ``nav_sight_m`` whose cell the field has free (it was not known then) and that lies near a shortest way
        from the agent, |p - agent| + d(p) <= d(agent) + 2 C + h (the straight distance is a lower bound of
        the way to p). Such a field would lead the agent on into what it now sees is closed (e.g. into a U
        whose far corners were beyond the sensor when the field was made)."""
        reach = (self.params.nav_sight_m, self.clearance_m)
        return _outdated(self.grid, rows, positions_m, obstacles_m, obstacle_mask, state, reach)

    def mark_dead_ends(
        self,
        rows: IntArray,
        positions_m: FloatArray,
        feasible: BoolArray,
        g_k: FloatArray,
        g0: FloatArray,
        state: NavState,
    ) -> BoolArray:
        """Block the cells of refused points that the potential says lead downhill (not the agent's own cell).
        Returns which rows gained a blocked cell (marking a blocked cell virtual changes later refreshes, not
        the field a refresh from the same points gives now)."""
        marked = np.zeros(rows.size, dtype=bool)
        for i, r in enumerate(rows):
            f = state.field[r]
            refused = ~feasible[i] & (g_k[i] < g0[i])
            if f is None or not refused.any():
                continue
            pts = positions_m[r, :2] + self._offsets[refused, :2]
            marked[i] = mark_dead_end(self.grid, f, positions_m[r, :2], pts)
        return marked

    def refresh(
        self,
        rows: IntArray,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: NavState,
    ) -> None:
        """Recompute the potential of ``rows`` from the obstacles known now plus the cells remembered before.

        A remembered cell blocked by an obstacle is kept only where no obstacle point known now lies within
        reach of it (``_reach_m``): there the points known now decide. A memory that forgets points (the
        service's expiry) keeps its walls in the grid, but a narrow door is not closed by the union of fields
        whose inflated edges jitter by a cell as the range noise moves its points (seen in a 1.5 m door at
        C = 0.6 m: a free column one cell wide, alternating between two columns). Dead ends (``virtual``) are
        always kept.

        A field that leaves the agent and its candidate points no way is computed again with the obstacles
        inflated by ``loose_m`` = C - h / 2 instead of C (the dead ends and the remembered cells as before): the
        lattice of cell centres alone can close a gap the vehicle passes (a 1.5 m door at C = 0.6 m leaves
        0.3 m, one cell, which range noise on the door's points closes; seen in `apf-sim fly --world rooms`,
        where the agent dithered for 36 s in a room its map had closed). The field's ``blocked`` stays the cells
        at C; moves keep C (the sweep), so a gap between 2 C - h and 2 C that this opens is refused at its
        mouth and closed by the dead-end rule.
        """
        grid = self.grid
        xy = positions_m[rows, :2]
        goals = targets_m[rows, :2]
        origins = grid.origins(xy, goals, self._pad_m)
        old_blocked, old_virtual = _carry_over(grid, [state.field[r] for r in rows], xy, origins, self._keep_m)
        obs_xy, valid = self._usable(rows, positions_m, obstacles_m, obstacle_mask)
        radii = (self.clearance_m, self._reach_m)
        inflated, known, keys, loose_cells = _occupancy(grid, radii, rows, origins, obs_xy, valid, state)
        blocked = inflated | (old_blocked & ~known) | old_virtual
        memos = [[] if state.field[r] is None else list(state.field[r].memo) for r in rows]
        dist, lost = self._distances(rows, xy, origins, blocked, goals, state, memos)
        if lost.any():  # closed in: again with the inflation loosened to C - h / 2 (``loose_m``)
            ix = np.flatnonzero(lost)
            loose = self._loose(ix, origins, obs_xy, valid, loose_cells) | (old_blocked[ix] & ~known[ix])
            dist[ix] = _recall(grid, [memos[k] for k in ix], origins[ix], loose | old_virtual[ix], goals[ix])
        for i, r in enumerate(rows):
            state.field[r] = NavField(
                origin_m=origins[i].copy(),
                blocked=blocked[i],
                dist_m=dist[i],
                virtual=old_virtual[i],
                memo=tuple(memos[i][-_MEMO:]),
                occupancy=(keys[i], inflated[i], known[i]),
                loose=loose_cells[i],
            )
        state.since_field[rows] = 0

    def _usable(
        self, rows: IntArray, positions_m: FloatArray, obstacles_m: FloatArray, obstacle_mask: BoolArray | None
    ) -> tuple[FloatArray, BoolArray]:
        """The points (R, M, 2) of ``rows`` that make their grids, zero where not valid, and which are valid (R, M):
        finite, in the mask and, in 3D, within C of the agent's altitude."""
        obs = obstacles_m[rows]
        valid: BoolArray = np.asarray(np.isfinite(obs).all(axis=2))
        if obstacle_mask is not None:
            valid &= obstacle_mask[rows]
        if self.params.dim == 3:
            valid &= np.abs(obs[:, :, 2] - positions_m[rows, 2][:, None]) <= self.clearance_m
        return np.where(valid[..., None], obs[:, :, :2], 0.0), valid

    def _loose(
        self,
        ix: IntArray,
        origins: FloatArray,
        obs_xy: FloatArray,
        valid: BoolArray,
        loose_cells: list[BoolArray | None],
    ) -> BoolArray:
        """The cells (len(ix), n^2) within ``loose_m`` of the points of rows ``ix``: the ones a field kept for the
        same points (``NavField.loose``), the others computed and written into ``loose_cells``."""
        todo = [k for k in ix if loose_cells[k] is None]
        if todo:
            fresh = self.grid.blocked(origins[todo], obs_xy[todo], valid[todo], self.loose_m)
            for k, cells in zip(todo, fresh, strict=True):
                loose_cells[k] = cells
        return np.stack([c for c in (loose_cells[k] for k in ix) if c is not None])  # every one set above

    def _distances(
        self,
        rows: IntArray,
        xy: FloatArray,
        origins: FloatArray,
        blocked: BoolArray,
        goals: FloatArray,
        state: NavState,
        memos: list[list[tuple[bytes, FloatArray]]],
    ) -> tuple[FloatArray, BoolArray]:
        """The fields of ``rows``, with the grid's edge closed where the agent has already looked beyond it, and
        which of them leave the agent and its candidate points no way (R,).

        An edge cell is an exit into unknown space (``navfield``): the way on from it costs only the straight
        line. Edge cells within ``nav_seen_m`` of the agent's trail are not unknown: that space was seen, and
        the agent turned back from it or came through it. Closing them keeps the potential from sending the
        agent back to a side it has explored once the grid, which moves with the agent, no longer holds what
        was there (a long wall: the agent would turn at every new grid). Fields are kept in the agent's
        memory without these closures. When they leave the agent and its candidate points no way, it is computed
        with the edge open.
        """
        seen_m = self.params.nav_seen_m if self.grid.exits else 0.0  # a flying area's grid has no exits
        closed = blocked
        if seen_m > 0.0:
            closed = _close_seen_edges(blocked, rows, origins, state, self._edge_cells, self._edge_centres, seen_m)
        dist = _recall(self.grid, memos, origins, closed, goals)
        lost = self._lost(xy, origins, dist)
        if seen_m > 0.0 and lost.any():
            ix = np.flatnonzero(lost)
            dist[ix] = _recall(self.grid, [memos[k] for k in ix], origins[ix], blocked[ix], goals[ix])
            lost[ix] = self._lost(xy[ix], origins[ix], dist[ix])
        return dist, lost

    def _lost(self, xy: FloatArray, origins: FloatArray, dist: FloatArray) -> BoolArray:
        """(R,) fields with no finite value at the agent (``xy``) nor at any of its candidate points."""
        around = xy[:, None, :] + np.vstack([self._offsets[:, :2], np.zeros((1, 2))])[None]
        return np.asarray(~_any(np.isfinite(self.grid.sample_many(origins, dist, around)), axis=1), dtype=np.bool_)

    def geodesic(
        self, rows: IntArray, positions_m: FloatArray, targets_m: FloatArray, state: NavState
    ) -> tuple[FloatArray, FloatArray]:
        """Potential at the points (R, K) and at the agents (R,) of ``rows`` (inf where unreachable)."""
        offsets = self._offsets
        pts = positions_m[rows][:, None, :] + np.vstack([offsets, np.zeros((1, offsets.shape[1]))])[None]
        fields = [state.field[r] for r in rows]
        origins = np.stack([f.origin_m for f in fields])
        values = self.grid.sample_many(origins, [f.dist_m for f in fields], pts[:, :, :2])
        if self.params.dim == 3:
            dz = pts[:, :, 2] - targets_m[rows, 2][:, None]
            values = np.sqrt(values * values + dz * dz)
        return values[:, :-1], values[:, -1]


def _outdated(
    grid: NavGrid,
    rows: IntArray,
    positions_m: FloatArray,
    obstacles_m: FloatArray,
    obstacle_mask: BoolArray | None,
    state: NavState,
    reach_m: tuple[float, float],
) -> BoolArray:
    """``EscapeMaps.outdated`` (its docstring has the rule); ``reach_m`` = (``nav_sight_m``, C). The distances, the
    near points and their cells for all rows at once (2D: the two products written out, einsum's sum bit for bit;
    3D: einsum per row, as before), the potential at the agents in one ``sample_many`` (element for element
    ``sample``'s); only the lookups in each agent's own field stay per row."""
    sight_m, clearance_m = reach_m
    out = np.zeros(rows.size, dtype=bool)
    fields = [state.field[r] for r in rows]
    idx = np.array([i for i, f in enumerate(fields) if f is not None], dtype=np.intp)
    if idx.size == 0:
        return out
    obs = obstacles_m[rows[idx]]
    rel = obs - positions_m[rows[idx]][:, None, :]
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite rows compare False below
        if rel.shape[2] == 2:
            d2 = rel[:, :, 0] * rel[:, :, 0]
            d2 += rel[:, :, 1] * rel[:, :, 1]
        else:
            d2 = np.stack([np.einsum("md,md->m", x, x) for x in rel])
    near = d2 <= sight_m**2
    if obstacle_mask is not None:
        near &= obstacle_mask[rows[idx]]
    if rel.shape[2] == 3:
        near &= np.abs(rel[:, :, 2]) <= clearance_m
    n = grid.n
    ci, cj = grid.cell_of(np.stack([fields[i].origin_m for i in idx]), obs[:, :, :2])
    inside = near & (ci >= 0) & (ci < n) & (cj >= 0) & (cj < n)
    cells = ci * n + cj
    todo: list[tuple[int, int, IntArray, BoolArray]] = []
    for k, i in enumerate(idx.tolist()):
        if inside[k].any():
            c = cells[k][inside[k]]
            new = ~fields[i].blocked[c]
            if new.any():
                todo.append((k, i, c, new))
    if not todo:
        return out
    sel = [fields[i] for _, i, _, _ in todo]
    where = positions_m[rows[[i for _, i, _, _ in todo]], :2][:, None, :]
    here = grid.sample_many(np.stack([f.origin_m for f in sel]), [f.dist_m for f in sel], where)[:, 0]
    slack = 2.0 * clearance_m + grid.cell_m
    for (k, i, c, new), f, h0 in zip(todo, sel, here, strict=True):
        if not np.isfinite(h0):
            out[i] = True
            continue
        way = np.sqrt(d2[k][inside[k]][new]) + f.dist_m[c[new]]
        out[i] = bool((way <= h0 + slack).any())
    return out


def _close_seen_edges(
    blocked: BoolArray,
    rows: IntArray,
    origins: FloatArray,
    state: NavState,
    edge_cells: IntArray,
    edge_centres: FloatArray,
    seen_m: float,
) -> BoolArray:
    """``blocked`` plus the edge cells within ``seen_m`` of each agent's trail (``EscapeMaps._distances``)."""
    closed = blocked.copy()
    for i, r in enumerate(rows):
        closed[i, seen_edge_cells(origins[i], state.trail_m[r], edge_cells, edge_centres, seen_m * seen_m)] = True
    return closed


def seen_edge_cells(
    origin_m: FloatArray, trail_m: FloatArray, edge_cells: IntArray, edge_centres: FloatArray, seen2_m2: float
) -> IntArray:
    """The edge cells of one grid (corner ``origin_m``) within sqrt(``seen2_m2``) of the trail (T, 2; NaN rows
    unused). Shared by the batch and the single-agent escape (``navescapeone``)."""
    # Only trail points near the ring of edge centres can be near one: not inside the ring's square shrunk by the
    # distance, nor outside it grown by the distance (a slack far above rounding keeps this test conservative; the
    # exact test below decides). Most of a trail lies inside the grid or far behind it, so the (E, T) test then
    # runs on a few points. The first and last edge cells are the grid's corners (0, 0) and (n - 1, n - 1).
    lo, hi = float(edge_centres[0, 0]), float(edge_centres[-1, 0])
    reach = math.sqrt(seen2_m2) + _SEEN_SLACK_M
    rel = trail_m - origin_m  # NaN rows (unused slots) compare False below
    outer = np.logical_and.reduce((rel >= lo - reach) & (rel <= hi + reach), axis=1)
    inner = np.logical_and.reduce((rel > lo + reach) & (rel < hi - reach), axis=1)
    trail = trail_m[outer & ~inner]
    if trail.shape[0] == 0:
        return edge_cells[:0]
    # (E, T) squared distances on coordinate planes: a sum of two products has one rounding, so this is einsum's
    # "ekd,ekd->ek" bit for bit, at a fraction of its cost on the short coordinate axis.
    centres = origin_m + edge_centres
    dx = centres[:, 0, None] - trail[None, :, 0]
    dy = centres[:, 1, None] - trail[None, :, 1]
    dx *= dx
    dy *= dy
    dx += dy
    return edge_cells[_any(dx < seen2_m2, axis=1)]


def mark_dead_end(grid: NavGrid, field: NavField, position_xy_m: FloatArray, points_xy_m: FloatArray) -> bool:
    """Mark the dead end of refused downhill points (P, 2) in ``field`` (blocked and virtual): their cells, not
    the agent's own. Where every such cell is blocked already, the points are downhill on the free corners of
    their bilinear stencils (``NavGrid.sample`` weighs the finite corners only), which lead on through the gap
    the sweep refuses (a diagonal between two inflated obstacles): those corners are marked instead. Without
    that, an agent beside such a gap sat with no point downhill until its patience ran out (6 of the 12000
    noise-free study trials). Returns whether a cell was newly blocked. Shared by the batch and the
    single-agent escape (``navescapeone``)."""
    n = grid.n
    ci, cj = grid.cell_of(field.origin_m[None], points_xy_m[None])
    own = grid.flat_cell(field.origin_m, position_xy_m)
    ok = (ci >= 0) & (ci < n) & (cj >= 0) & (cj < n)
    cells = ci[ok] * n + cj[ok]
    cells = cells[cells != own]
    if field.blocked[cells].all():  # a cell already blocked only turns virtual: the same field
        corners = grid.corner_cells(field.origin_m, points_xy_m)
        corners = corners[(corners != own) & ~field.blocked[corners] & np.isfinite(field.dist_m[corners])]
        cells = np.concatenate([cells, corners])
    marked = not field.blocked[cells].all()
    field.blocked[cells] = True
    field.virtual[cells] = True
    return marked


def own_cell_blocked(grid: NavGrid, field: NavField | None, position_xy_m: FloatArray) -> bool:
    """Whether the agent's own cell is blocked in ``field`` (off the grid or no field: True). An agent with no
    value on its field is inside the inflated obstacles when its cell is blocked (noise put it there: it backs
    out), and closed in when its cell is free (no way: it gives up, Design item 7). Shared by the batch and the
    single-agent escape step."""
    if field is None:
        return True
    cell = grid.flat_cell(field.origin_m, position_xy_m)
    return cell < 0 or bool(field.blocked[cell])


def occupancy_key(origin_m: FloatArray, obs_xy_m: FloatArray, valid: BoolArray) -> bytes:
    """The exact input of one agent's occupancy cells (``NavField.occupancy``): corner, points, valid flags."""
    return origin_m.tobytes() + obs_xy_m.tobytes() + valid.tobytes()


def field_key(origin_m: FloatArray, goal_xy_m: FloatArray, blocked: BoolArray) -> bytes:
    """The exact input of one field (``NavField.memo``): corner, goal, packed blocked cells."""
    return origin_m.tobytes() + goal_xy_m.tobytes() + np.packbits(blocked).tobytes()


def _occupancy(
    grid: NavGrid,
    radii_m: tuple[float, float],
    rows: IntArray,
    origins: FloatArray,
    obs_xy: FloatArray,
    valid: BoolArray,
    state: NavState,
) -> tuple[BoolArray, BoolArray, list[bytes], list[BoolArray | None]]:
    """Cells within the clearance and within the reach (``radii_m``) of the points known now (R, n^2) each, and
    their exact input per agent; taken from the agent's field (``NavField.occupancy``) when that input is the same
    (a second refresh in one step: the stall or dead-end rule), with the loosened cells the field keeps for that
    input (``NavField.loose``; None where there are none)."""
    inflated = np.empty((rows.size, grid.size), dtype=bool)
    known = np.empty((rows.size, grid.size), dtype=bool)
    keys = [occupancy_key(origins[i], obs_xy[i], valid[i]) for i in range(rows.size)]
    loose: list[BoolArray | None] = [None] * rows.size
    todo = []
    for i, r in enumerate(rows):
        f = state.field[r]
        if f is not None and f.occupancy is not None and f.occupancy[0] == keys[i]:
            inflated[i], known[i], loose[i] = f.occupancy[1], f.occupancy[2], f.loose
        else:
            todo.append(i)
    if todo:
        inflated[todo], known[todo] = grid.blocked_within(origins[todo], obs_xy[todo], valid[todo], radii_m)
    return inflated, known, keys, loose


def _recall(
    grid: NavGrid,
    memos: list[list[tuple[bytes, FloatArray]]],
    origins: FloatArray,
    blocked: BoolArray,
    goals: FloatArray,
) -> FloatArray:
    """``NavGrid.distances``, taken from an agent's memo (``NavField.memo``) when it holds the same input; new
    fields are appended to the memo (the caller keeps the last ``_MEMO``)."""
    out = np.empty(blocked.shape)
    for i, memo in enumerate(memos):
        key = field_key(origins[i], goals[i], blocked[i])
        known = [d for k, d in memo if k == key]
        if known:
            out[i] = known[0]
        else:
            out[i] = grid.distances(origins[i : i + 1], blocked[i : i + 1], goals[i : i + 1])[0]
            memo.append((key, out[i].copy()))
    return out


def _carry_over(
    grid: NavGrid, old_fields: list[NavField | None], xy_m: FloatArray, origins_m: FloatArray, pad_m: float
) -> tuple[BoolArray, BoolArray]:
    """The remembered blocked and virtual cells (B, n^2) of the old fields in the new grids. An agent well inside
    its old grid (``pad_m`` from every side) keeps that frame: ``origins_m`` is updated in place."""
    old_blocked = np.zeros((len(old_fields), grid.size), dtype=bool)
    old_virtual = np.zeros((len(old_fields), grid.size), dtype=bool)
    side = grid.n * grid.cell_m
    for i, old in enumerate(old_fields):
        if old is None:
            continue
        rel = xy_m[i] - old.origin_m
        if np.all(rel >= pad_m) and np.all(rel <= side - pad_m):
            origins_m[i] = old.origin_m  # the agent is well inside: keep the frame
            old_blocked[i], old_virtual[i] = old.blocked, old.virtual
        else:  # a new frame: carry the remembered cells over where the grids overlap
            old_blocked[i] = grid.shift_blocked(old.blocked, old.origin_m, origins_m[i])
            old_virtual[i] = grid.shift_blocked(old.virtual, old.origin_m, origins_m[i])
    return old_blocked, old_virtual
