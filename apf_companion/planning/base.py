"""The planner interface: ``step`` for one agent is ``step_batch`` with A = 1."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.planning.decision import BatchDecision, Decision
from apf_companion.planning.geometry import bacteria_offsets
from apf_companion.planning.params import PlannerParams

__all__ = ["Planner"]

FloatArray = npt.NDArray[np.float64]


class Planner(ABC):
    """A planner: given where the agent is, where it goes and the obstacles it knows, decide the next point.

    Positions are in any Cartesian frame (the service passes local NED; 2D uses north/east), metres. A planner
    holds no state between steps: noise, collision, goal and obstacle-memory rules belong to the caller.
    """

    name: ClassVar[str]

    def __init__(self, params: PlannerParams) -> None:
        if not isinstance(params, PlannerParams):
            raise ConfigError(f"params = {params!r} is invalid; allowed: a PlannerParams")
        self.params = params
        offsets = bacteria_offsets(params.n_bacteria, params.step_m, params.dim)
        offsets.setflags(write=False)
        #: (N_b, D) bacteria point offsets from the agent [m]; ``chosen_index`` indexes these rows.
        self.bacteria_offsets_m: FloatArray = offsets

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})"

    def step(
        self,
        position_m: npt.ArrayLike,
        target_m: npt.ArrayLike,
        obstacles_m: npt.ArrayLike,
        rng: np.random.Generator | None = None,
    ) -> Decision:
        """One agent's step.

        Parameters
        ----------
        position_m : (D,) agent position r [m].
        target_m : (D,) target r_t [m].
        obstacles_m : (N, D) known obstacle points [m]; N may be 0.
        rng : source of the random walk (CR-BAPF* only; others ignore it).
        """
        pos, tgt, obs = self._check_one(position_m, target_m, obstacles_m)
        return self._step_batch(pos[None], tgt[None], obs[None], None, rng, None).row(0)

    def _check_one(
        self, position_m: npt.ArrayLike, target_m: npt.ArrayLike, obstacles_m: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``step``'s arguments as validated float64 arrays ((D,), (D,), (N, D))."""
        dim = self.params.dim
        pos = np.asarray(position_m, dtype=np.float64)
        tgt = np.asarray(target_m, dtype=np.float64)
        obs = np.asarray(obstacles_m, dtype=np.float64)
        if pos.shape != (dim,) or tgt.shape != (dim,):
            raise ConfigError(f"position_m and target_m must have shape ({dim},); got {pos.shape}, {tgt.shape}")
        if obs.size == 0:
            obs = obs.reshape(0, dim)
        if obs.ndim != 2 or obs.shape[1] != dim:
            raise ConfigError(f"obstacles_m must have shape (N, {dim}); got {obs.shape}")
        return pos, tgt, obs

    def step_batch(
        self,
        positions_m: npt.ArrayLike,
        targets_m: npt.ArrayLike,
        obstacles_m: npt.ArrayLike,
        obstacle_mask: npt.ArrayLike,
        rng: np.random.Generator | None = None,
        *,
        walk_uniforms: npt.ArrayLike | None = None,
    ) -> BatchDecision:
        """A step of A agents at once (the study's lockstep engine; ``step`` is this with A = 1).

        Parameters
        ----------
        positions_m : (A, D) float64 agent positions [m].
        targets_m : (A, D) float64 targets [m].
        obstacles_m : (A, N, D) float64 obstacle points per agent [m].
        obstacle_mask : (A, N) bool; True where obstacle n is known to agent a (padding: False).
        rng : random-walk source (CR-BAPF* only): one ``rng.random()`` per agent that needs a walk, in agent
            order.
        walk_uniforms : optional (A,) floats in [0, 1) used for the random walk instead of ``rng`` (one per
            agent, used only where a walk is needed), so a caller can give each agent its own stream.
        """
        pos, tgt, obs, mask = self._check_batch(positions_m, targets_m, obstacles_m, obstacle_mask)
        n_agents = pos.shape[0]
        uniforms = None
        if walk_uniforms is not None:
            uniforms = np.asarray(walk_uniforms, dtype=np.float64)
            if uniforms.shape != (n_agents,):
                raise ConfigError(f"walk_uniforms must have shape ({n_agents},); got {uniforms.shape}")
        return self._step_batch(pos, tgt, obs, mask, rng, uniforms)

    def _check_batch(
        self,
        positions_m: npt.ArrayLike,
        targets_m: npt.ArrayLike,
        obstacles_m: npt.ArrayLike,
        obstacle_mask: npt.ArrayLike,
    ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """``step_batch``'s arrays, validated: (A, D), (A, D), (A, N, D) float64 and the (A, N) bool mask."""
        dim = self.params.dim
        pos = np.asarray(positions_m, dtype=np.float64)
        tgt = np.asarray(targets_m, dtype=np.float64)
        obs = np.asarray(obstacles_m, dtype=np.float64)
        mask = np.asarray(obstacle_mask, dtype=bool)
        if pos.ndim != 2 or pos.shape[1] != dim or tgt.shape != pos.shape:
            raise ConfigError(f"positions_m and targets_m must have shape (A, {dim}); got {pos.shape}, {tgt.shape}")
        n_agents = pos.shape[0]
        if obs.size == 0:
            obs = obs.reshape(n_agents, 0, dim)
            mask = mask.reshape(n_agents, 0)
        if obs.shape[::2] != (n_agents, dim) or obs.ndim != 3 or mask.shape != obs.shape[:2]:
            raise ConfigError(
                f"obstacles_m must be (A, N, {dim}) and obstacle_mask (A, N) with A = {n_agents}; "
                f"got {obs.shape}, {mask.shape}"
            )
        return pos, tgt, obs, mask

    @abstractmethod
    def _step_batch(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: npt.NDArray[np.bool_] | None,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        """The algorithm, on validated float64 arrays; ``obstacle_mask`` None means every obstacle is known."""
