"""Bacteria points: the candidate next positions around the agent (Diab et al. 2023, Sec. "BAPF", Fig. 1).

2D: a ring of N_b points at angles k * 360 / N_b degrees, k = 1..N_b, in the world frame (angle measured from
the frame's +x axis toward +y), as in the authors' code. 3D: N_b points spread evenly on a sphere by a Fibonacci
lattice (docs/paper/notes.md decision 6). The radius is the movement step Delta r.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError

__all__ = ["bacteria_offsets", "bacteria_ring", "bacteria_sphere"]

_GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))


def _check(n_points: int, radius_m: float, minimum: int) -> None:
    if isinstance(n_points, bool) or not isinstance(n_points, int | np.integer) or n_points < minimum:
        raise ConfigError(f"n_points = {n_points!r} is invalid; allowed: an int >= {minimum}")
    if not math.isfinite(radius_m) or radius_m <= 0.0:
        raise ConfigError(f"radius_m = {radius_m!r} is invalid; allowed: a finite number > 0")


def bacteria_ring(n_points: int, radius_m: float) -> npt.NDArray[np.float64]:
    """Offsets of a 2D ring of bacteria points around the agent.

    Parameters
    ----------
    n_points : N_b >= 3.
    radius_m : ring radius, the step Delta r [m].

    Returns
    -------
    (N_b, 2) float64 offsets; row k-1 is at angle k * 2 pi / N_b from +x toward +y (k = 1..N_b), so the
    last row points along +x exactly.
    """
    _check(n_points, radius_m, 3)
    k = np.arange(1, n_points + 1) % n_points  # k = N_b is angle 0: keeps that point exactly on +x
    angle_rad = 2.0 * math.pi * k / n_points
    return radius_m * np.stack([np.cos(angle_rad), np.sin(angle_rad)], axis=-1)


def bacteria_sphere(n_points: int, radius_m: float) -> npt.NDArray[np.float64]:
    """Offsets of N_b bacteria points spread evenly on a sphere (Fibonacci lattice).

    Point i (0-based) has z = radius * (1 - (2 i + 1) / N_b) and azimuth i * golden angle, so the points cover
    equal-area bands and never coincide with the poles.

    Returns
    -------
    (N_b, 3) float64 offsets, each of norm ``radius_m``.
    """
    _check(n_points, radius_m, 4)
    i = np.arange(n_points, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n_points
    r_xy = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    azimuth_rad = i * _GOLDEN_ANGLE_RAD
    unit = np.stack([r_xy * np.cos(azimuth_rad), r_xy * np.sin(azimuth_rad), z], axis=-1)
    return radius_m * unit


def bacteria_offsets(n_points: int, radius_m: float, dim: int) -> npt.NDArray[np.float64]:
    """The ring (dim = 2) or the sphere (dim = 3)."""
    if dim == 2:
        return bacteria_ring(n_points, radius_m)
    if dim == 3:
        return bacteria_sphere(n_points, radius_m)
    raise ConfigError(f"dim = {dim!r} is invalid; allowed: 2 or 3")
