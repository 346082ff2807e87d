"""Per-agent memory of bapf-nav (``BapfNavPlanner``): mode, progress, last move, and the navigation potential."""

from __future__ import annotations

import enum
from dataclasses import dataclass, fields
from typing import Self

import numpy as np
import numpy.typing as npt

__all__ = ["TRAIL", "GiveUp", "NavField", "NavMode", "NavState"]

FloatArray = npt.NDArray[np.float64]
#: Trail points kept per agent (``NavState.trail_m``): at 1 m apart, the last 64 m of the way.
TRAIL = 64


class NavMode(enum.IntEnum):
    """What drives an agent's choice (``NavState.mode``)."""

    #: Straight-line distance to the target (Eq. (1)) plus clearance: the paper's greedy bacteria step.
    DIRECT = 0
    #: Geodesic distance on the remembered map: while a remembered surface blocks the straight line, or after a
    #: trap; until the line is clear and the agent is closer than where the escape began.
    ESCAPE = 1
    #: Gave up (no path on the remembered map, or no progress): no moves until the target changes.
    GAVE_UP = 2


class GiveUp(enum.IntEnum):
    """Why an agent gave up (``NavState.gave_up``): the service's STUCK says it to the pilot."""

    #: Not given up.
    NONE = 0
    #: No way to the target on the remembered map: the agent's region is closed (at C and at C - h / 2).
    NO_WAY = 1
    #: No new closest approach to the target for ``nav_patience_steps`` steps.
    NO_PROGRESS = 2
    #: The target lies outside the flying area (``nav_area_ne_m``).
    OUTSIDE_AREA = 3

    @property
    def text(self) -> str:
        """What a pilot reads (STATUSTEXT): the cause in a few words (no way on the remembered map: the region is
        closed; no new closest approach for ``nav_patience_steps``; the target outside ``nav_area_ne_m``)."""
        return _GIVE_UP_TEXT[self]


#: Short: "APF STUCK: planner gave up: <text>" must fit the 50 characters of one STATUSTEXT.
_GIVE_UP_TEXT = {
    GiveUp.NONE: "not given up",
    GiveUp.NO_WAY: "no way on the map",
    GiveUp.NO_PROGRESS: "no progress",
    GiveUp.OUTSIDE_AREA: "goal outside area",
}


@dataclass(slots=True)
class NavField:
    """One agent's navigation potential: grid corner, remembered blocked cells and the distances to the goal."""

    origin_m: FloatArray  # (2,) lower corner (north, east) [m]
    blocked: npt.NDArray[np.bool_]  # (n^2,) every blocked cell: inflated obstacles and ``virtual``
    dist_m: FloatArray  # (n^2,) geodesic distance to the goal [m]; inf where blocked or unreachable
    virtual: npt.NDArray[np.bool_]  # (n^2,) dead ends marked by the planner (no obstacle point behind them)
    #: The last few fields computed for this agent, by their exact input (corner, goal, packed blocked cells):
    #: a recomputation from the same input (the stall and dead-end rules often meet an unchanged map) reuses
    #: one instead of running Dijkstra again. Values are bit-identical either way.
    memo: tuple[tuple[bytes, FloatArray], ...] = ()
    #: The cells within the clearance and within the reach of the points (``navescape._occupancy``) and their
    #: exact input (corner, points, valid flags): a second refresh from the same points reuses them.
    occupancy: tuple[bytes, npt.NDArray[np.bool_], npt.NDArray[np.bool_]] | None = None
    #: The cells within ``EscapeMaps.loose_m`` of the same points, once a refresh needed them (closed in), else
    #: None: a second refresh from the same points reuses them too.
    loose: npt.NDArray[np.bool_] | None = None


@dataclass(slots=True)
class NavState:
    """Rows of agents (see ``stateful.AgentState``). ``field`` is an object array of ``NavField`` or None."""

    target_m: FloatArray  # (A, D) target the memory belongs to (NaN: none yet)
    mode: npt.NDArray[np.int8]  # (A,) NavMode
    hit_dist_m: FloatArray  # (A,) straight-line distance to the target where the escape began [m]
    best_dist_m: FloatArray  # (A,) closest approach to the target so far [m]
    since_best: npt.NDArray[np.int32]  # (A,) steps since the closest approach improved
    since_field: npt.NDArray[np.int32]  # (A,) steps since the potential was computed (kept after an escape)
    prev_dir: FloatArray  # (A, D) unit direction of the last move (zeros: none)
    field: npt.NDArray[np.object_]  # (A,) NavField | None
    trail_m: FloatArray  # (A, TRAIL, 2) where the agent has been (north, east), about 1 m apart; NaN: unused
    trail_next: npt.NDArray[np.int32]  # (A,) slot the next trail point goes to (a ring buffer)
    gave_up: npt.NDArray[np.int8]  # (A,) GiveUp: why the agent is in GAVE_UP mode (NONE otherwise)

    @classmethod
    def empty(cls, n_agents: int, dim: int) -> NavState:
        return cls(
            target_m=np.full((n_agents, dim), np.nan),
            mode=np.zeros(n_agents, dtype=np.int8),
            hit_dist_m=np.full(n_agents, np.inf),
            best_dist_m=np.full(n_agents, np.inf),
            since_best=np.zeros(n_agents, dtype=np.int32),
            since_field=np.zeros(n_agents, dtype=np.int32),
            prev_dir=np.zeros((n_agents, dim)),
            field=np.full(n_agents, None, dtype=object),
            trail_m=np.full((n_agents, TRAIL, 2), np.nan),
            trail_next=np.zeros(n_agents, dtype=np.int32),
            gave_up=np.zeros(n_agents, dtype=np.int8),
        )

    def __len__(self) -> int:
        return int(self.mode.shape[0])

    def take(self, rows: npt.NDArray[np.intp] | npt.NDArray[np.bool_]) -> Self:
        return type(self)(**{f.name: getattr(self, f.name)[rows].copy() for f in fields(self)})

    def put(self, rows: npt.NDArray[np.intp], other: Self) -> None:
        for f in fields(self):
            getattr(self, f.name)[rows] = getattr(other, f.name)

    def restart(self, rows: npt.NDArray[np.intp], targets_m: FloatArray) -> None:
        """Forget everything about ``rows`` (a new target)."""
        self.target_m[rows] = targets_m
        self.mode[rows] = NavMode.DIRECT
        self.hit_dist_m[rows] = np.inf
        self.best_dist_m[rows] = np.inf
        self.since_best[rows] = 0
        self.since_field[rows] = 0
        self.prev_dir[rows] = 0.0
        self.field[rows] = None
        self.trail_m[rows] = np.nan
        self.trail_next[rows] = 0
        self.gave_up[rows] = GiveUp.NONE

    def record(self, positions_m: FloatArray, spacing_m: float) -> None:
        """Add each agent's position (north, east) to its trail when it is ``spacing_m`` from the last point."""
        last = self.trail_m[np.arange(len(self)), (self.trail_next - 1) % TRAIL]
        delta = positions_m[:, :2] - last
        far = ~(np.einsum("ad,ad->a", delta, delta) < spacing_m * spacing_m)  # NaN (no point yet): record
        rows = np.flatnonzero(far)
        if rows.size:
            self.trail_m[rows, self.trail_next[rows]] = positions_m[rows, :2]
            self.trail_next[rows] = (self.trail_next[rows] + 1) % TRAIL
