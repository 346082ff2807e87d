"""The paper's performance metrics (Section "Performance Metrics") and outcome bookkeeping.

- R_s = N_s / N_m, Eq. (14), over all trials, with a Wilson score 95 % interval.
- M_s, the mean number of iterations over successful trials (docs/paper/notes.md: iterations, including ones without a
  move and the final one inside the goal circle).
- S, Eq. (16): per successful trial, the mean over the obstacles detected during the run of the minimum
  distance from the visited positions; then averaged over successful trials.
- T_a, the mean wall-clock time per trial [ms] (in the lockstep engine: a chunk's wall time divided by its
  trials, so it is the amortised cost of a trial, not the latency of one trial run alone; per trial, the chunk's
  time is split in proportion to the iterations each trial ran).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

Z_95 = 1.959963984540054
"""Two-sided 95 % standard-normal quantile."""


class Outcome(enum.IntEnum):
    """How a trial ended."""

    SUCCESS = 0
    """Within the goal radius at the start of an iteration."""
    COLLISION = 1
    """Closer than the collision radius to an obstacle at the start of an iteration."""
    STUCK = 2
    """A local minimum the planner cannot leave (BAPF family), or CAPF's stuck rule."""
    TIMEOUT = 3
    """Still running after the iteration cap."""


@dataclass(frozen=True, slots=True, kw_only=True)
class TrialRecords:
    """Per-trial results of a set of trials (one chunk, or chunks concatenated in order)."""

    outcome: npt.NDArray[np.int8]
    """(A,) Outcome codes."""
    iterations: npt.NDArray[np.int32]
    """(A,) iterations run (M_s for successful trials)."""
    safety_m: npt.NDArray[np.float64]
    """(A,) S of the trial, Eq. (16) [m]; NaN if no obstacle was ever detected."""
    n_obstacles: npt.NDArray[np.int32]
    """(A,) obstacles in the world."""
    n_detected: npt.NDArray[np.int32]
    """(A,) distinct obstacles detected during the run."""
    time_ms: npt.NDArray[np.float64]
    """(A,) amortised wall-clock time of the trial [ms] (not deterministic)."""
    path_m: npt.NDArray[np.float64] | None = None
    """(A,) length of the flown path, noise included [m] (None: not recorded)."""
    clearance_m: npt.NDArray[np.float64] | None = None
    """(A,) smallest distance from a visited position to a true obstacle surface [m] (None: not recorded)."""

    def __len__(self) -> int:
        return int(self.outcome.shape[0])

    def rows(self, lo: int, hi: int) -> TrialRecords:
        """Trials [lo, hi) (views)."""

        def cut(a: npt.NDArray[Any] | None) -> Any:
            return None if a is None else a[lo:hi]

        return TrialRecords(**{f.name: cut(getattr(self, f.name)) for f in fields(self)})

    @staticmethod
    def concat(parts: list[TrialRecords]) -> TrialRecords:
        if not parts:
            return TrialRecords(
                outcome=np.zeros(0, np.int8),
                iterations=np.zeros(0, np.int32),
                safety_m=np.zeros(0),
                n_obstacles=np.zeros(0, np.int32),
                n_detected=np.zeros(0, np.int32),
                time_ms=np.zeros(0),
            )
        return TrialRecords(
            outcome=np.concatenate([p.outcome for p in parts]),
            iterations=np.concatenate([p.iterations for p in parts]),
            safety_m=np.concatenate([p.safety_m for p in parts]),
            n_obstacles=np.concatenate([p.n_obstacles for p in parts]),
            n_detected=np.concatenate([p.n_detected for p in parts]),
            time_ms=np.concatenate([p.time_ms for p in parts]),
            path_m=_concat_optional([p.path_m for p in parts]),
            clearance_m=_concat_optional([p.clearance_m for p in parts]),
        )


def _concat_optional(parts: list[npt.NDArray[np.float64] | None]) -> npt.NDArray[np.float64] | None:
    """The concatenation when every part recorded the field, else None."""
    present = [p for p in parts if p is not None]
    return np.concatenate(present) if len(present) == len(parts) else None


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion; (0, 1) when there are no trials."""
    if trials <= 0:
        return (0.0, 1.0)
    p = successes / trials
    z2 = z * z
    denom = 1.0 + z2 / trials
    centre = (p + z2 / (2.0 * trials)) / denom
    half = z * math.sqrt(p * (1.0 - p) / trials + z2 / (4.0 * trials * trials)) / denom
    # The bounds are exactly 0 / 1 at the extremes; the formula reaches them only up to rounding.
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == trials else min(1.0, centre + half)
    return (lo, hi)


@dataclass(frozen=True, slots=True, kw_only=True)
class Summary:
    """The paper's metrics over a set of trials."""

    trials: int
    R_s: float
    R_s_ci95: tuple[float, float]
    M_s: float
    """Mean iterations over successful trials (NaN if none)."""
    S: float
    """Mean safety distance over successful trials [m] (NaN if none)."""
    T_a_ms: float
    """Mean wall-clock time per trial [ms]."""
    success: int
    collision: int
    stuck: int
    timeout: int

    def to_json(self) -> dict[str, object]:
        def num(x: float) -> float | None:
            return None if math.isnan(x) else float(x)

        return {
            "trials": self.trials,
            "R_s": self.R_s,
            "R_s_ci95": [self.R_s_ci95[0], self.R_s_ci95[1]],
            "M_s": num(self.M_s),
            "S": num(self.S),
            "T_a_ms": num(self.T_a_ms),
            "counts": {
                "success": self.success,
                "collision": self.collision,
                "stuck": self.stuck,
                "timeout": self.timeout,
            },
        }


def _nanmean(values: npt.NDArray[np.float64]) -> float:
    finite = values[~np.isnan(values)]
    return float(finite.mean()) if finite.size else math.nan


def summarize(records: TrialRecords) -> Summary:
    """R_s (Eq. (14)) over all trials; M_s and S (Eq. (16)) over successful ones; T_a over all."""
    n = len(records)
    counts = np.bincount(records.outcome.astype(np.int64), minlength=len(Outcome))
    ok = records.outcome == Outcome.SUCCESS
    n_ok = int(counts[Outcome.SUCCESS])
    return Summary(
        trials=n,
        R_s=n_ok / n if n else math.nan,
        R_s_ci95=wilson_interval(n_ok, n),
        M_s=float(records.iterations[ok].mean()) if n_ok else math.nan,
        S=_nanmean(records.safety_m[ok]),
        T_a_ms=float(records.time_ms.mean()) if n else math.nan,
        success=n_ok,
        collision=int(counts[Outcome.COLLISION]),
        stuck=int(counts[Outcome.STUCK]),
        timeout=int(counts[Outcome.TIMEOUT]),
    )


def safety_per_trial(
    min_distance_m: npt.NDArray[np.float64], detected: npt.NDArray[np.bool_]
) -> npt.NDArray[np.float64]:
    """S of each trial, Eq. (16): mean over detected obstacles of the minimum distance from the visited
    positions.

    Parameters
    ----------
    min_distance_m : (A, N) minimum distance from any visited position to each obstacle [m].
    detected : (A, N) bool, the obstacle was detected at some point of the run.

    Returns
    -------
    (A,) float64 [m], NaN for a trial that detected nothing.
    """
    n = detected.sum(axis=1)
    total = np.where(detected, min_distance_m, 0.0).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out: npt.NDArray[np.float64] = np.where(n > 0, total / np.maximum(n, 1), np.nan)
    return out
