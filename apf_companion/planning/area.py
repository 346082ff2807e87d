"""The flying area (``PlannerParams.nav_area_ne_m``): which points lie in it.

One rule for every user of the area: the escape grid's blocked cells and its goal (``navfield``), bapf-nav's give-up
on a target outside it (``bapfnav``), the service's refusal of such goals (``goal.route_outside_limits``) and the
world files' check of their start and goal (``sim.world``). Bounds inclusive; a non-finite coordinate is outside.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["AreaNE", "inside_area"]

#: (north_min, east_min, north_max, east_max) in local NED [m].
AreaNE = tuple[float, float, float, float]


def inside_area(area_ne_m: AreaNE, north_m: npt.ArrayLike, east_m: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Whether each point (``north_m``, ``east_m``, broadcast together) lies in the area, bounds included."""
    n_min, e_min, n_max, e_max = area_ne_m
    north, east = np.asarray(north_m, dtype=np.float64), np.asarray(east_m, dtype=np.float64)
    inside: npt.NDArray[np.bool_] = (n_min <= north) & (north <= n_max) & (e_min <= east) & (east <= e_max)
    return inside
