"""bapf-nav's single-agent refresh of an escape field (``navescapeone.FieldOne``): ``EscapeMaps.refresh`` of
one agent on 1-D arrays, the same field bit for bit.

The rules are the batch path's (``navescape``): the grid's frame kept while the agent is well inside it, else
moved with the remembered and virtual cells carried over; the occupancy of the points known now (reused from the
field when its input is the same); the edge cells the trail has seen closed; the agent's field memo; and, for an
agent that its field closes in, the field again with the inflation loosened. The candidate points' values are
sampled through ``FieldOne``'s per-step sampling (injected), so a field is sampled once in a step.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from apf_companion.planning.navescape import _MEMO, EscapeMaps, field_key, occupancy_key, seen_edge_cells
from apf_companion.planning.navone import einsum
from apf_companion.planning.navstate import NavField, NavState

__all__ = ["RefreshOne"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: ``FieldOne._sampled``: a field (corner, distances) at the candidate points and the agent around ``xy``.
Sampler = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]


class RefreshOne:
    """``EscapeMaps.refresh`` of one agent (module docstring); the owner of the trail-closure and all-valid caches.

    Parameters
    ----------
    maps : the planner's escape maps (grid, parameters, edge cells).
    sampled : ``FieldOne._sampled``, the per-step sampling at the candidate points and the agent.
    """

    def __init__(self, maps: EscapeMaps, sampled: Sampler) -> None:
        p = maps.params
        self._grid = maps.grid
        self._h = maps.grid.cell_m
        self._side_m = maps.grid.n * maps.grid.cell_m
        self._dim = p.dim
        self._seen2 = p.nav_seen_m * p.nav_seen_m if maps.grid.exits else 0.0  # a flying area's grid: no exits
        self._clearance_m = maps.clearance_m
        self._radii_m = (maps.clearance_m, maps._reach_m)
        self._loose_m = maps.loose_m
        self._keep_m = maps._keep_m
        self._half_room_m = max(self._side_m / 2.0 - max(maps._pad_m, self._side_m / 3.0), 0.0)
        self._edge_cells = maps._edge_cells
        self._edge_centres = maps._edge_centres
        self._sampled = sampled
        #: The last input (corner and trail, as bytes) of ``_close_seen_edges`` and its edge cells to close.
        self._seen_key = b""
        self._seen_cells = self._edge_cells[:0]
        self._all_valid = np.ones(0, dtype=bool)

    def __call__(
        self, position_m: FloatArray, target_m: FloatArray, obstacles_m: FloatArray, state: NavState
    ) -> FloatArray | None:
        """``EscapeMaps.refresh`` of one agent. Returns the new field at the points and the agent (K + 1,) where
        the ``lost`` check sampled it (the field kept), else None."""
        xy, goal = position_m[:2], target_m[:2]
        old = state.field[0]
        origin, old_blocked, old_virtual = self._carry_over(old, xy, goal)
        obs_xy, valid = self._usable(position_m, obstacles_m)
        key = occupancy_key(origin, obs_xy, valid)
        loose_cells = None
        if old is not None and old.occupancy is not None and old.occupancy[0] == key:
            inflated, known, loose_cells = old.occupancy[1], old.occupancy[2], old.loose
        else:
            cells = self._grid.blocked_within(origin[None], obs_xy[None], valid[None], self._radii_m)
            inflated, known = cells[0][0], cells[1][0]
        # Nothing remembered: the points known now (a copy: dead ends are marked in the field's own cells).
        blocked = inflated.copy() if old_blocked is None else inflated | (old_blocked & ~known) | old_virtual
        memo = [] if old is None else list(old.memo)
        dist, values = self._distances(xy, origin, blocked, goal, state, memo)
        if values is None:  # closed in: again with the inflation loosened (``EscapeMaps.loose_m``)
            if loose_cells is None:  # not kept from a refresh of the same points (``NavField.loose``)
                loose_cells = self._grid.blocked(origin[None], obs_xy[None], valid[None], self._loose_m)[0]
            loose = loose_cells
            if old_blocked is not None and old_virtual is not None:
                loose = loose | (old_blocked & ~known) | old_virtual
            dist = self._recall(memo, origin, loose, goal)
        state.field[0] = NavField(
            origin_m=origin,
            blocked=blocked,
            dist_m=dist,
            virtual=np.zeros(self._grid.size, dtype=bool) if old_virtual is None else old_virtual,
            memo=tuple(memo[-_MEMO:]),
            occupancy=(key, inflated, known),
            loose=loose_cells,
        )
        state.since_field[0] = 0
        return values

    def _usable(self, position_m: FloatArray, obstacles_m: FloatArray) -> tuple[FloatArray, BoolArray]:
        """The points (M, 2) that make the grid, zero where not valid, and which are valid (M,): finite and, in
        3D, within C of the agent's altitude (``EscapeMaps.refresh``). 2D and all finite: the points as given."""
        if self._dim == 2 and np.isfinite(obstacles_m).all():
            if self._all_valid.shape[0] != obstacles_m.shape[0]:
                self._all_valid = np.ones(obstacles_m.shape[0], dtype=bool)  # only read (keys, occupancy)
            return obstacles_m, self._all_valid
        valid = np.logical_and.reduce(np.isfinite(obstacles_m), axis=1)
        if self._dim == 3:
            valid &= np.abs(obstacles_m[:, 2] - position_m[2]) <= self._clearance_m
        return np.where(valid[:, None], obstacles_m[:, :2], 0.0), valid

    def _origin(self, xy_m: FloatArray, goal_m: FloatArray) -> FloatArray:
        """``NavGrid.origins`` of one agent in Python floats: the same operations on each coordinate (the
        distance is the batch path's einsum on the same layout)."""
        if self._grid.fixed_origin_m is not None:
            return self._grid.fixed_origin_m.copy()
        delta = goal_m - xy_m
        dist = float(np.sqrt(einsum("bd,bd->b", delta[None], delta[None]))[0])
        side, h = self._side_m, self._h
        reach = min(dist / 2.0, self._half_room_m)
        out = []
        for x, d in zip(xy_m.tolist(), delta.tolist(), strict=True):
            unit = d / dist if dist > 0.0 else 0.0
            out.append(math.floor((x + unit * reach - side / 2.0) / h) * h)
        return np.array(out)

    def _carry_over(
        self, old: NavField | None, xy_m: FloatArray, goal_m: FloatArray
    ) -> tuple[FloatArray, BoolArray | None, BoolArray | None]:
        """``navescape._carry_over`` of one agent: the grid's corner (the old one where the agent is well inside
        it, else ``NavGrid.origins``'s) and the remembered blocked and virtual cells in that grid (None: no old
        field). The blocked cells are only read; the virtual ones become the new field's (a copy)."""
        if old is None:
            return self._origin(xy_m, goal_m), None, None
        pad, far = self._keep_m, self._side_m - self._keep_m
        if all(pad <= x - o <= far for x, o in zip(xy_m.tolist(), old.origin_m.tolist(), strict=True)):
            return old.origin_m.copy(), old.blocked, old.virtual.copy()  # well inside: keep the frame
        origin_m = self._origin(xy_m, goal_m)
        return (
            origin_m,
            self._grid.shift_blocked(old.blocked, old.origin_m, origin_m),
            self._grid.shift_blocked(old.virtual, old.origin_m, origin_m),
        )

    def _distances(
        self,
        xy_m: FloatArray,
        origin_m: FloatArray,
        blocked: BoolArray,
        goal_m: FloatArray,
        state: NavState,
        memo: list[tuple[bytes, FloatArray]],
    ) -> tuple[FloatArray, FloatArray | None]:
        """``EscapeMaps._distances`` of one agent: the field, and its values at the points and the agent (None:
        no finite value, the agent is closed in)."""
        closed = self._close_seen_edges(blocked, origin_m, state) if self._seen2 > 0.0 else blocked
        dist = self._recall(memo, origin_m, closed, goal_m)
        values = self._sampled(origin_m, dist, xy_m)
        if np.isfinite(values).any():
            return dist, values
        if self._seen2 > 0.0:  # again with the edge open
            dist = self._recall(memo, origin_m, blocked, goal_m)
            values = self._sampled(origin_m, dist, xy_m)
            if np.isfinite(values).any():
                return dist, values
        return dist, None

    def _close_seen_edges(self, blocked: BoolArray, origin_m: FloatArray, state: NavState) -> BoolArray:
        """``navescape._close_seen_edges`` of one agent. The edge cells to close depend only on the grid's corner
        and the trail, which change every few steps: the last answer is kept with its exact input."""
        key = origin_m.tobytes() + state.trail_m[0].tobytes()
        if key != self._seen_key:
            cells = seen_edge_cells(origin_m, state.trail_m[0], self._edge_cells, self._edge_centres, self._seen2)
            self._seen_key, self._seen_cells = key, cells
        if self._seen_cells.size == 0:
            return blocked
        closed = blocked.copy()
        closed[self._seen_cells] = True
        return closed

    def _recall(
        self, memo: list[tuple[bytes, FloatArray]], origin_m: FloatArray, blocked: BoolArray, goal_m: FloatArray
    ) -> FloatArray:
        """``navescape._recall`` of one agent: the field from the memo when it holds the same input, else new
        (appended to the memo)."""
        key = field_key(origin_m, goal_m, blocked)
        for k, d in memo:
            if k == key:
                return d
        dist: FloatArray = self._grid.distances(origin_m[None], blocked[None], goal_m[None])[0]
        memo.append((key, dist))
        return dist
