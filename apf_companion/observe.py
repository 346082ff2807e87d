"""Read-only observers of the service cycle (the visualisation's way in; apf_companion.viz is one).

After each cycle the service hands every observer a ``CycleSnapshot``: what the cycle decided (``CycleOutput``),
the pose, the route, the remembered obstacle points, the newest scan's points and the latest planner step with
its candidates (``PlanStep``). Everything is in local NED [m]. An observer only reads; planning stays pure (the
planner step is seen through ``PlanTap``, which delegates unchanged).

An observer must never slow or end the cycle: ``Observers`` builds the snapshot only when there is an observer,
and an exception raised by one is counted (``handler_errors`` via ``FaultLog``) and logged once per kind, and the
cycle goes on.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from apf_companion.goal import Route
from apf_companion.navigator import CycleOutput, DecisionLike, Navigator, PlannerLike
from apf_companion.perception import PerceptionFrontEnd, Pose
from apf_companion.planning import Planner
from apf_companion.reporter import FaultLog

__all__ = ["CycleObserver", "CycleSnapshot", "Observers", "PlanStep", "PlanTap"]

FloatArray = npt.NDArray[np.float64]
log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, kw_only=True)
class PlanStep:
    """One planner step as the navigator made it.

    Attributes:
        seq: Planner steps so far (1 for the first); tells a new step from one seen before.
        origin_m: (D,) where it planned from (the bacteria point just reached, or the pose), local NED [m].
        target_m: (D,) the waypoint it planned towards, local NED [m].
        candidates_m: (N_b, D) the bacteria points it scored: ``origin_m`` + the planner's offsets [m].
        decision: The planner's decision (``apf_companion.planning.Decision`` for the bundled planners: reason,
            ``chosen_index``, ``candidate_cost``).
    """

    seq: int
    origin_m: FloatArray
    target_m: FloatArray
    candidates_m: FloatArray
    decision: DecisionLike


class PlanTap:
    """Wraps a planner: ``step`` delegates unchanged and keeps its inputs and decision (``plan()``); every other
    attribute is the planner's.

    Keeping them costs a tuple per step; the ``PlanStep`` (with the candidates) is built only when observed.
    """

    def __init__(self, planner: Planner) -> None:
        self.planner = planner
        self.seq = 0
        self._last: tuple[FloatArray, FloatArray, DecisionLike] | None = None

    def __getattr__(self, name: str) -> Any:
        """Everything else (``params``, ``clearance_m``, ...) is the planner's own."""
        return getattr(self.planner, name)

    def step(
        self, position_m: FloatArray, target_m: FloatArray, obstacles_m: FloatArray, rng: np.random.Generator
    ) -> DecisionLike:
        decision = self.planner.step(position_m, target_m, obstacles_m, rng)
        self.seq += 1
        self._last = (position_m, target_m, decision)
        return decision

    def plan(self) -> PlanStep | None:
        """The latest step, or None before the first."""
        if self._last is None:
            return None
        origin, target, decision = self._last
        candidates = origin + self.planner.bacteria_offsets_m
        return PlanStep(seq=self.seq, origin_m=origin, target_m=target, candidates_m=candidates, decision=decision)


@dataclass(frozen=True, slots=True, kw_only=True)
class CycleSnapshot:
    """What one cycle saw and decided (read-only; arrays are the owners' copies or their own frozen arrays).

    Attributes:
        out: The cycle's output (state, setpoint sent or None, decision, distances, state changes).
        pose: The latest accepted pose (local NED), or None before the first.
        route: The active route, or None.
        target_ned_m: (3,) the waypoint being flown to, or None.
        obstacles_ned_m: (N, 3) remembered obstacle points.
        scan_ned_m: (M, 3) the points the newest usable scan added.
        plan: The latest planner step (it may be from an earlier cycle while the vehicle flies to its point).
    """

    out: CycleOutput
    pose: Pose | None
    route: Route | None
    target_ned_m: FloatArray | None
    obstacles_ned_m: FloatArray
    scan_ned_m: FloatArray
    plan: PlanStep | None


class CycleObserver(Protocol):
    """Something that watches the cycle (``apf_companion.viz.FoxgloveSink``)."""

    def on_cycle(self, snap: CycleSnapshot) -> None: ...

    def close(self) -> None: ...


class Observers:
    """The service's observers: builds the snapshot once per cycle, fans it out, contains their faults
    (``errors`` counts them; each is also in the service's ``handler_errors`` and logged once per kind)."""

    def __init__(self, faults: FaultLog) -> None:
        self.observers: list[CycleObserver] = []
        self.faults = faults
        self.errors = 0
        self._tap: PlanTap | None = None

    def tap(self, planner: Planner) -> PlannerLike:
        """The planner the navigator calls: ``planner`` behind a ``PlanTap`` (the newest one is observed)."""
        old, self._tap = self._tap, PlanTap(planner)
        if old is not None:  # a planner swapped at run time (PARAM_SET, the fence): the step count goes on
            self._tap.seq = old.seq
        return self._tap

    def add(self, observers: Sequence[CycleObserver]) -> None:
        self.observers.extend(observers)

    def _caught(self, what: str, err: Exception) -> None:
        self.errors += 1
        self.faults.caught(what, err)

    def cycle(self, out: CycleOutput, navigator: Navigator, perception: PerceptionFrontEnd) -> None:
        """Tell every observer about this cycle; a failing observer is counted and the others still run."""
        if not self.observers:
            return
        try:
            snap = CycleSnapshot(
                out=out,
                pose=navigator.pose,
                route=navigator.route,
                target_ned_m=navigator.active_target_ned_m,
                obstacles_ned_m=perception.points(out.t_s),
                scan_ned_m=perception.latest_scan_ned_m,
                plan=None if self._tap is None else self._tap.plan(),
            )
        except Exception as err:
            self._caught("observe", err)
            return
        for obs in self.observers:
            try:
                obs.on_cycle(snap)
            except Exception as err:
                self._caught(f"observe.{type(obs).__name__}", err)

    def close(self) -> None:
        """Close every observer (files finished, servers stopped); errors are counted, never raised."""
        for obs in self.observers:
            try:
                obs.close()
            except Exception as err:
                self._caught(f"observe.{type(obs).__name__}", err)
