"""A noise-free ray-cast scanner with a point memory over a World: the planner harness of the tests and benchmarks.

72 rays (every 5 degrees) reach ``range_m`` = 8 m; every return is remembered, one per ``merge_m`` = 0.1 m lattice
cell (the first return kept), in the order first seen. Planners get the whole memory each step, as the service's
obstacle memory gives them its points (without the service's expiry, noise and sectors). Used by
``tests/planning`` (bundled world flights, the decision digest) and ``benchmarks/area_paths.py``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from sim.world.model import World

__all__ = ["SCAN_BEARINGS_RAD", "ScanMemory"]

FloatArray = npt.NDArray[np.float64]

#: The scanner's ray bearings [rad from north, clockwise]: 72 rays, 5 degrees apart.
SCAN_BEARINGS_RAD = np.radians(np.arange(0.0, 360.0, 5.0))


class ScanMemory:
    """Scans ``world`` from given positions and remembers every return (module docstring).

    Parameters
    ----------
    world : the obstacles; range_m : the rays' reach [m]; merge_m : lattice of the memory [m].
    """

    def __init__(self, world: World, range_m: float = 8.0, merge_m: float = 0.1) -> None:
        self.world = world
        self.range_m = range_m
        self.merge_m = merge_m
        self._points: dict[tuple[int, int], FloatArray] = {}

    def scan(self, pos_ne_m: FloatArray) -> FloatArray:
        """Scan from ``pos_ne_m`` (north, east; more coordinates ignored) and return the memory (M, 2), local NED."""
        pos = pos_ne_m[:2]
        ranges = self.world.ray_cast_m(pos, SCAN_BEARINGS_RAD)
        hit = ranges <= self.range_m
        bearings = SCAN_BEARINGS_RAD[hit]
        returns = pos + ranges[hit, None] * np.stack([np.cos(bearings), np.sin(bearings)], axis=1)
        for q in returns:
            self._points.setdefault((round(q[0] / self.merge_m), round(q[1] / self.merge_m)), q)
        return self.cloud()

    def cloud(self) -> FloatArray:
        """Every remembered return (M, 2) in the order first seen."""
        return np.array(list(self._points.values())) if self._points else np.zeros((0, 2))
