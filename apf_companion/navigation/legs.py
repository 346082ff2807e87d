"""The route's legs: which waypoint is flown to, and the progress towards it (for the give-up rules)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from apf_companion.goal import Route
from apf_companion.navigation.model import FloatArray, NavigatorParams
from apf_companion.navigation.tracking import StepTracker

__all__ = ["PROGRESS_EPS_M", "Leg", "Legs"]

PROGRESS_EPS_M = 0.1  # a new best distance to the goal must beat the old by this much to count as progress


@dataclass(slots=True)
class Leg:
    index: int
    target_ned_m: FloatArray  # (3,), down resolved
    best_dist_m: float = math.inf
    best_t_s: float = 0.0
    streak: int = 0  # consecutive non-greedy decisions


class Legs:
    """The route's legs: which waypoint is flown to, and the progress towards it (for the give-up rules)."""

    def __init__(self, params: NavigatorParams, steps: StepTracker) -> None:
        self.p = params
        self.steps = steps
        self.leg: Leg | None = None

    def distance(self, a: FloatArray, b: FloatArray) -> float:
        d = a[: self.p.dim] - b[: self.p.dim]
        return float(np.sqrt(d @ d))

    def provisional_distance(self, route: Route, pos: FloatArray) -> float:
        """Distance to the active waypoint; before the leg starts (it is fixed only once the autopilot is engaged,
        so a takeoff in between sets the altitude that is kept) to the first waypoint at the current altitude."""
        if self.leg is not None:
            return self.distance(pos, self.leg.target_ned_m)
        first = route.waypoints_ned_m[0]
        return self.distance(pos, np.where(np.isnan(first), pos, first))

    def current(self, route: Route, pos: FloatArray, now_s: float) -> tuple[Leg | None, float]:
        """The leg to fly and the distance to its waypoint; (None, distance) once the last one is reached."""
        leg = self.leg if self.leg is not None else self._start(route, 0, pos, now_s)
        dist = self.distance(pos, leg.target_ned_m)
        while dist <= self.p.arrival_radius_m:
            if leg.index + 1 >= len(route):
                return None, dist
            leg = self._start(route, leg.index + 1, pos, now_s)
            dist = self.distance(pos, leg.target_ned_m)
        # Progress bookkeeping (time-based give-up, docs/paper/notes.md decision 7).
        if dist < leg.best_dist_m - PROGRESS_EPS_M or math.isinf(leg.best_dist_m):
            leg.best_dist_m = dist
            leg.best_t_s = now_s
        return leg, dist

    def _start(self, route: Route, index: int, pos: FloatArray, now_s: float) -> Leg:
        target = np.array(route.waypoints_ned_m[index], dtype=np.float64)
        if math.isnan(target[2]):
            target[2] = pos[2]  # keep the altitude this leg starts at
        self.leg = Leg(index=index, target_ned_m=target, best_t_s=now_s)
        self.steps.target = None
        return self.leg

    def give_up(self, leg: Leg, now_s: float) -> str | None:
        if leg.streak > self.p.random_walk_budget:
            return f"stuck: no greedy move for {leg.streak} cycles"
        if now_s - leg.best_t_s > self.p.progress_timeout_s:
            return f"stuck: no progress for {now_s - leg.best_t_s:.0f} s"
        return None
