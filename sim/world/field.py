"""The paper's random obstacle field (Diab et al. 2023, Sec. IV; project decisions in docs/paper/notes.md).

Point obstacles uniformly distributed in a square: preset ``reference`` draws them in [5, 20]^2 m (the authors'
published code), preset ``paper`` in [0, 30]^2 m (the paper's text). The agent starts at (3, 3) and the target
is (22, 22) (north, east metres). The obstacle count N is drawn per trial from a discrete uniform density range
(``low`` U[20, 45], ``mid`` U[45, 70], ``high`` U[70, 95]) or given directly.

The draw is exactly::

    n = rng.integers(lo, hi, endpoint=True)          # only when a density name is given
    obstacles_ne_m = rng.uniform(a, b, size=(n, 2))  # columns: north, east

so anyone holding the same seed can regenerate the same field.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from apf_companion.errors import ConfigError
from sim.world.model import World

__all__ = [
    "DENSITIES",
    "FIELD_PRESETS",
    "MAX_OBSTACLES",
    "PAPER_START_NE_M",
    "PAPER_TARGET_NE_M",
    "FieldPreset",
    "paper_field",
    "parse_field_spec",
]

PAPER_START_NE_M = (3.0, 3.0)
PAPER_TARGET_NE_M = (22.0, 22.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class FieldPreset:
    """Where the random point obstacles are drawn: uniform in [lo_m, hi_m]^2 (north and east)."""

    name: str
    lo_m: float
    hi_m: float


FIELD_PRESETS: dict[str, FieldPreset] = {
    "reference": FieldPreset(name="reference", lo_m=5.0, hi_m=20.0),
    "paper": FieldPreset(name="paper", lo_m=0.0, hi_m=30.0),
}

# The study's obstacle-count ranges N ~ U{N_l, N_u} (inclusive).
DENSITIES: dict[str, tuple[int, int]] = {"low": (20, 45), "mid": (45, 70), "high": (70, 95)}
#: The most obstacles a field may have.
MAX_OBSTACLES = 100_000


def paper_field(
    preset: str,
    n_obstacles: int | str,
    rng: np.random.Generator,
    *,
    radius_m: float = 0.0,
) -> World:
    """A random field of the paper's kind.

    Args:
        preset: ``reference`` ([5, 20]^2) or ``paper`` ([0, 30]^2).
        n_obstacles: the number of obstacles, or a density name (``low``/``mid``/``high``) to draw it.
        rng: the only source of randomness.
        radius_m: obstacle radius [m] (0 = the paper's point obstacles).

    Returns:
        A World with start (3, 3) and goal (22, 22).
    """
    try:
        spec = FIELD_PRESETS[preset]
    except KeyError as err:
        msg = f"paper field preset must be one of {sorted(FIELD_PRESETS)}, got {preset!r}"
        raise ConfigError(msg) from err
    if isinstance(n_obstacles, str):
        if n_obstacles not in DENSITIES:
            msg = f"paper field density must be one of {sorted(DENSITIES)} or an integer, got {n_obstacles!r}"
            raise ConfigError(msg)
        lo, hi = DENSITIES[n_obstacles]
        n = int(rng.integers(lo, hi, endpoint=True))
    else:
        n = int(n_obstacles)
    if not 0 <= n <= MAX_OBSTACLES:
        msg = f"paper field obstacle count must be in [0, {MAX_OBSTACLES}], got {n}"
        raise ConfigError(msg)
    if not radius_m >= 0:
        msg = f"paper field radius_m must be >= 0, got {radius_m}"
        raise ConfigError(msg)
    pts = rng.uniform(spec.lo_m, spec.hi_m, size=(n, 2))
    return World.from_obstacles(
        pts,
        radius_m,
        name=f"paper-field:{preset}:{n}",
        start_ne_m=PAPER_START_NE_M,
        goal_ne_m=PAPER_TARGET_NE_M,
    )


def parse_field_spec(spec: str) -> tuple[str, int | str]:
    """Parse ``PRESET:N`` or ``PRESET:DENSITY`` (e.g. ``reference:40``, ``paper:mid``)."""
    preset, sep, count = spec.partition(":")
    if not sep or preset not in FIELD_PRESETS:
        msg = f"--paper-field must be PRESET:N with PRESET in {sorted(FIELD_PRESETS)}, got {spec!r}"
        raise ConfigError(msg)
    if count in DENSITIES:
        return preset, count
    try:
        return preset, int(count)
    except ValueError as err:
        msg = f"--paper-field count must be an integer or one of {sorted(DENSITIES)}, got {count!r}"
        raise ConfigError(msg) from err
