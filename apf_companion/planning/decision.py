"""What a planner step returns: one agent (``Decision``) or a batch of agents (``BatchDecision``)."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

__all__ = ["BatchDecision", "Decision", "DecisionReason", "filled"]

_ScalarT = TypeVar("_ScalarT", bound=np.generic)


def filled(n: int, value: float, dtype: type[_ScalarT]) -> npt.NDArray[_ScalarT]:
    """A new (n,) array of ``value`` (cheaper than ``np.full`` for the tiny arrays of a single step)."""
    if n == 1:
        return np.array([value], dtype=dtype)
    out = np.empty(n, dtype=dtype)
    out.fill(value)
    return out


class DecisionReason(enum.IntEnum):
    """Why the agent moves (or not); the int values are the int8 codes of ``BatchDecision.reason``."""

    #: A bacteria point passed Eq. (6) (CAPF: a step along the negative gradient).
    GREEDY = 0
    #: No point passed; CR-BAPF* took a random-walk step to a safe point.
    RANDOM_WALK = 1
    #: No move: no point passed (and no random-walk move was possible), or the CAPF gradient vanished.
    LOCAL_MINIMUM = 2
    #: No move, and none will come: a stateful planner's give-up rule fired (bapf-nav: no path on the
    #: remembered map, or no progress for ``nav_patience_steps``). The caller should report STUCK.
    GAVE_UP = 3


#: DecisionReason by int code (a tuple lookup is cheaper than the Enum call in the single-agent step).
_REASONS: tuple[DecisionReason, ...] = tuple(sorted(DecisionReason, key=int))


@dataclass(frozen=True, slots=True, kw_only=True)
class Decision:
    """One agent's step.

    Attributes
    ----------
    next_point_m : (D,) float64 next position, or None when the agent does not move.
    reason : why.
    chosen_index : 0-based index of the chosen bacteria point (row of ``bacteria_offsets_m``), or None.
    mu_o_k : A-BAPF: mu_o,k of the chosen point (Eq. (11)) [1/m^2]; None for other planners or no move.
    n_passing : how many bacteria points passed Eq. (6) (0 for CAPF, which has none).
    n_safe : how many bacteria points are at least rho_l from every known obstacle (the random walk's set Q);
        -1 when the planner does not compute it.
    candidate_cost : (N_b,) float64 score of each bacteria point, lower is better [m]; +inf where the point
        fails the move test. None when the planner does not report it (bapf-nav does: its J_k).
    """

    next_point_m: npt.NDArray[np.float64] | None
    reason: DecisionReason
    chosen_index: int | None = None
    mu_o_k: float | None = None
    n_passing: int = 0
    n_safe: int = -1
    candidate_cost: npt.NDArray[np.float64] | None = None

    @property
    def moved(self) -> bool:
        """True when the agent has a next point."""
        return self.next_point_m is not None

    @property
    def gave_up(self) -> bool:
        """True when the planner's give-up rule fired (``DecisionReason.GAVE_UP``)."""
        return self.reason is DecisionReason.GAVE_UP


@dataclass(frozen=True, slots=True, kw_only=True)
class BatchDecision:
    """A step of A agents at once; row a is agent a. Same meaning as ``Decision``, as arrays.

    Attributes
    ----------
    next_points_m : (A, D) float64; NaN rows where the agent does not move.
    reason : (A,) int8 codes of ``DecisionReason``.
    chosen_index : (A,) int64; -1 for none.
    mu_o_k : (A,) float64; NaN unless A-BAPF moved.
    n_passing : (A,) int64.
    n_safe : (A,) int64; -1 when not computed.
    candidate_cost : (A, N_b) float64 or None.
    """

    next_points_m: npt.NDArray[np.float64]
    reason: npt.NDArray[np.int8]
    chosen_index: npt.NDArray[np.int64]
    mu_o_k: npt.NDArray[np.float64]
    n_passing: npt.NDArray[np.int64]
    n_safe: npt.NDArray[np.int64]
    candidate_cost: npt.NDArray[np.float64] | None = None

    @property
    def moved(self) -> npt.NDArray[np.bool_]:
        """(A,) True where the agent has a next point."""
        return np.asarray(self.reason < DecisionReason.LOCAL_MINIMUM)

    def row(self, index: int) -> Decision:
        """Agent ``index`` as a ``Decision``."""
        reason = _REASONS[int(self.reason[index])]
        chosen = int(self.chosen_index[index])
        mu = float(self.mu_o_k[index])
        return Decision(
            next_point_m=None if reason >= DecisionReason.LOCAL_MINIMUM else self.next_points_m[index].copy(),
            reason=reason,
            chosen_index=chosen if chosen >= 0 else None,
            mu_o_k=None if mu != mu else mu,  # NaN: none
            n_passing=int(self.n_passing[index]),
            n_safe=int(self.n_safe[index]),
            candidate_cost=None if self.candidate_cost is None else self.candidate_cost[index].copy(),
        )
