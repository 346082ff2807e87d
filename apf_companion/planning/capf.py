"""CAPF: classical artificial potential field, Khatib-style (Khatib 1985), as this project defines it.

The paper (Diab et al. 2023, DOI 10.1109/AERO55745.2023.10115857) compares against a "CAPF" but gives no formula
(its reference, Mohanta 2016, could not be located); docs/paper/notes.md fixes this field:

    U_att = k_att d^2 / 2,   d = |r - r_t|
    U_rep = sum_n eta (1/rho_n - 1/rho_0)^2 / 2   for rho_n < rho_0 (0 beyond), rho_n = |r - r_o^n| (FIRAS)

and the agent takes a fixed step of ``step_m`` along the negative gradient. A vanishing (or undefined) gradient
is a local minimum. The "no new best distance for 60 iterations" stuck rule is the caller's.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apf_companion.planning.base import Planner
from apf_companion.planning.decision import BatchDecision, DecisionReason, filled
from apf_companion.planning.params import PlannerParams

__all__ = ["CapfPlanner", "capf_force"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: The gradient "vanishes" when its norm is below this fraction of the sum of the norms of its parts.
_VANISHING_RATIO = np.array(1e-12)
_LOCAL_MINIMUM_CODE = np.array(DecisionReason.LOCAL_MINIMUM, dtype=np.int8)


def capf_force(
    positions_m: FloatArray,
    targets_m: FloatArray,
    obstacles_m: FloatArray,
    obstacle_mask: BoolArray | None,
    *,
    k_att: float,
    eta: float,
    rho_0_m: float,
) -> tuple[FloatArray, FloatArray]:
    """-grad(U_att + U_rep) at each agent, and the sum of the norms of its parts (for the vanishing test).

    Shapes: positions/targets (A, D), obstacles (A, N, D), mask (A, N) or None (all known). Returns (A, D)
    and (A,). Work arrays are (D, A, N), so ufuncs run along the obstacle axis.
    """
    n_agents = positions_m.shape[0]
    force = (targets_m - positions_m) * np.array(k_att)  # attraction; the repulsion is added below
    scale = np.sqrt(np.add.reduce(force * force, axis=1))
    by_axis = obstacles_m.transpose(2, 0, 1)
    if n_agents > 8:
        by_axis = np.ascontiguousarray(by_axis)  # contiguous (A, N) per axis: fast ufunc loops
    rel = positions_m.T[:, :, None] - by_axis  # (D, A, N), obstacle -> agent
    dist_m = np.sqrt(np.add.reduce(rel * rel, axis=0))
    active = dist_m < np.array(rho_0_m)
    if obstacle_mask is not None:
        active &= obstacle_mask
    # |F_rep,n| = eta (1/rho - 1/rho_0) / rho^2, along (r - r_o) / rho: coef = eta (1/rho - 1/rho_0) / rho^3.
    # Inactive pairs get 1/rho = 0 (never computed), so coef = 0; an obstacle at rho = 0 gives inf, and the
    # NaN force that follows makes the step a local minimum (the direction is undefined).
    inv_m = np.zeros(dist_m.shape)
    np.divide(1.0, dist_m, out=inv_m, where=active)
    coef = (inv_m - np.array(1.0 / rho_0_m)) * np.array(eta)
    coef *= inv_m * inv_m * inv_m
    force += np.add.reduce(coef * rel, axis=2).T
    scale += np.add.reduce(np.abs(coef) * dist_m, axis=1)
    return force, scale


class CapfPlanner(Planner):
    """CAPF (module docstring): a fixed step along -grad U; no bacteria points."""

    name = "capf"

    def __init__(self, params: PlannerParams) -> None:
        super().__init__(params)
        self._step = np.array(params.step_m)

    def _step_batch(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        p = self.params
        n_agents = positions_m.shape[0]
        force, scale = capf_force(
            positions_m,
            targets_m,
            obstacles_m,
            obstacle_mask,
            k_att=p.capf_k_att,
            eta=p.capf_eta,
            rho_0_m=p.capf_rho_0_m,
        )
        norm = np.sqrt(np.add.reduce(force * force, axis=1))
        # False for a zero gradient (norm 0 <= 0), a vanishing one, and NaN or inf (obstacle at rho = 0).
        stuck = ~(norm > _VANISHING_RATIO * scale)
        norm[stuck] = 1.0
        force *= (self._step / norm)[:, None]
        next_points = positions_m + force
        next_points[stuck] = np.nan
        return BatchDecision(
            next_points_m=next_points,
            reason=stuck.view(np.int8) * _LOCAL_MINIMUM_CODE,  # GREEDY = 0, LOCAL_MINIMUM = 2
            chosen_index=filled(n_agents, -1, np.int64),
            mu_o_k=filled(n_agents, np.nan, np.float64),
            n_passing=filled(n_agents, 0, np.int64),
            n_safe=filled(n_agents, -1, np.int64),
        )
