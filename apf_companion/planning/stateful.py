"""Planners with memory: per-agent state that the caller owns in batches, and the planner owns for ``step``.

``step_batch(..., state=S)`` reads and updates ``S`` in place (row a is agent a); the caller keeps ``S`` with its
agents: ``S.take(rows)`` when agents leave the batch, ``S.put(rows, sub)`` after planning a subset. Without
``state`` every agent starts fresh (its first step). ``step`` keeps one agent's state inside the planner, so a
caller written for the stateless planners (``planner.step(position, target, obstacles, rng)``) works unchanged;
``reset()`` forgets it, and a new target starts afresh by itself.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import Protocol, Self

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.planning.base import Planner
from apf_companion.planning.decision import BatchDecision, Decision
from apf_companion.planning.params import PlannerParams

__all__ = ["AgentState", "StatefulPlanner", "decision_from_choice"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def decision_from_choice(
    positions_m: npt.NDArray[np.float64],
    offsets_m: npt.NDArray[np.float64],
    chosen: npt.NDArray[np.integer],
    reason: npt.NDArray[np.int8],
    n_passing: npt.NDArray[np.integer],
    n_safe: npt.NDArray[np.integer],
    candidate_cost: npt.NDArray[np.float64] | None = None,
) -> BatchDecision:
    """The batch decision of agents that move to bacteria point ``chosen`` (row of ``offsets_m``; -1: no move);
    ``candidate_cost`` (A, N_b): each point's score, +inf where it does not pass (``BatchDecision``)."""
    next_points = positions_m + offsets_m[chosen]  # rows with chosen = -1 are overwritten below
    next_points[chosen < 0] = np.nan
    mu_o_k = np.empty(positions_m.shape[0])
    mu_o_k.fill(np.nan)
    return BatchDecision(
        next_points_m=next_points,
        reason=reason,
        chosen_index=np.asarray(chosen, dtype=np.int64),
        mu_o_k=mu_o_k,
        n_passing=np.asarray(n_passing, dtype=np.int64),
        n_safe=np.asarray(n_safe, dtype=np.int64),
        candidate_cost=candidate_cost,
    )


class AgentState(Protocol):
    """Per-agent planner memory, row a = agent a."""

    def __len__(self) -> int: ...

    def take(self, rows: npt.NDArray[np.intp] | BoolArray) -> Self:
        """A copy of the given rows (index array or bool mask)."""
        ...

    def put(self, rows: npt.NDArray[np.intp], other: Self) -> None:
        """Write ``other``'s rows into ``rows`` of this state."""
        ...


class StatefulPlanner(Planner):
    """A planner whose decision depends on the agent's history (``AgentState``)."""

    def __init__(self, params: PlannerParams) -> None:
        super().__init__(params)
        self._own: AgentState | None = None

    def reset(self) -> None:
        """Forget the single-agent state of ``step`` (a new flight)."""
        self._own = None

    @property
    def own_state(self) -> AgentState | None:
        """The single-agent state of ``step`` (None before the first step): read it, e.g. for the mode."""
        return self._own

    @abstractmethod
    def initial_state(self, n_agents: int) -> AgentState:
        """The state of ``n_agents`` agents before their first step."""

    @abstractmethod
    def _plan(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: AgentState,
    ) -> BatchDecision:
        """The algorithm on validated arrays; updates ``state`` in place."""

    def step(
        self,
        position_m: npt.ArrayLike,
        target_m: npt.ArrayLike,
        obstacles_m: npt.ArrayLike,
        rng: np.random.Generator | None = None,
    ) -> Decision:
        """One agent's step, with the planner's own memory of this agent (``reset()`` forgets it)."""
        pos, tgt, obs, own = self._one(position_m, target_m, obstacles_m)
        return self._plan(pos[None], tgt[None], obs[None], None, own).row(0)

    def _one(
        self, position_m: npt.ArrayLike, target_m: npt.ArrayLike, obstacles_m: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray, AgentState]:
        """One agent's validated arrays and the planner's own memory of it (created on first use)."""
        pos, tgt, obs = self._check_one(position_m, target_m, obstacles_m)
        if self._own is None:
            self._own = self.initial_state(1)
        return pos, tgt, obs, self._own

    def step_batch(
        self,
        positions_m: npt.ArrayLike,
        targets_m: npt.ArrayLike,
        obstacles_m: npt.ArrayLike,
        obstacle_mask: npt.ArrayLike,
        rng: np.random.Generator | None = None,
        *,
        walk_uniforms: npt.ArrayLike | None = None,
        state: AgentState | None = None,
    ) -> BatchDecision:
        """A step of A agents; ``state`` (A rows, updated in place) carries their memory between calls.

        ``rng`` and ``walk_uniforms`` are accepted for the common interface; these planners draw nothing.
        """
        pos, tgt, obs, mask = self._check_batch(positions_m, targets_m, obstacles_m, obstacle_mask)
        st = state if state is not None else self.initial_state(pos.shape[0])
        if len(st) != pos.shape[0]:
            raise ConfigError(f"state has {len(st)} rows for {pos.shape[0]} agents")
        return self._plan(pos, tgt, obs, mask, st)

    def _step_batch(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        return self._plan(positions_m, targets_m, obstacles_m, obstacle_mask, self.initial_state(positions_m.shape[0]))
