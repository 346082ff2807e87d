"""Random point-obstacle fields for the Monte Carlo study (paper, "Simulation Setup").

Each trial draws its obstacle count N ~ discrete U[N_l, N_u] (inclusive) and N obstacle points uniform
continuous in the preset's box. A batch of trials is padded to ``(A, N_u, D)`` with a boolean mask; the padding
rows are drawn too (and ignored), so the draws of trial ``a`` depend only on the generator's state, not on the
counts of other trials.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from sim.study.config import Density, ObstacleSampling


@dataclass(frozen=True, slots=True, kw_only=True)
class WorldBatch:
    """Obstacle fields of A trials."""

    obstacles_m: npt.NDArray[np.float64]
    """(A, N_max, D) float64 obstacle points [m]; rows past a trial's count are padding."""
    mask: npt.NDArray[np.bool_]
    """(A, N_max) bool, True for a real obstacle."""

    @property
    def counts(self) -> npt.NDArray[np.int64]:
        """(A,) number of real obstacles per trial."""
        counts: npt.NDArray[np.int64] = self.mask.sum(axis=1).astype(np.int64)
        return counts


def draw_worlds(
    rng: np.random.Generator,
    n_trials: int,
    density: Density,
    box_m: tuple[float, float],
    dim: int = 2,
    sampling: ObstacleSampling = ObstacleSampling.CONTINUOUS,
) -> WorldBatch:
    """Draw ``n_trials`` obstacle fields.

    Parameters
    ----------
    rng : the chunk's world generator (consumed: counts first, then all points).
    n_trials : A, number of trials.
    density : obstacle-count range [N_l, N_u].
    box_m : (low, high) of the uniform box on every axis [m].
    dim : D, 2 or 3.
    sampling : continuous coordinates, or integer ones with repeated points dropped (masked out).
    """
    counts = rng.integers(density.n_low, density.n_high, endpoint=True, size=n_trials)
    low, high = box_m
    mask = np.arange(density.n_high)[None, :] < counts[:, None]
    if sampling is ObstacleSampling.CONTINUOUS:
        points = rng.uniform(low, high, size=(n_trials, density.n_high, dim))
        return WorldBatch(obstacles_m=points, mask=mask)
    lattice = rng.integers(math.ceil(low), math.floor(high), endpoint=True, size=(n_trials, density.n_high, dim))
    points = lattice.astype(np.float64)
    # A point equal to an earlier real point of the same trial is a duplicate: mask it out.
    same = np.all(points[:, :, None, :] == points[:, None, :, :], axis=-1)  # (A, N, N)
    earlier = np.tril(np.ones((density.n_high, density.n_high), dtype=bool), k=-1)
    duplicate = np.any(same & earlier[None] & mask[:, None, :], axis=2)
    return WorldBatch(obstacles_m=points, mask=mask & ~duplicate)
