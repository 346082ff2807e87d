"""CR-BAPF and CR-BAPF*: changing-radii bacteria APF, with and without random walk (Diab et al. 2023).

Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered Environments",
IEEE Aerospace 2023, DOI 10.1109/AERO55745.2023.10115857. Repulsion: Eq. (13) (0 beyond rho_u, +inf inside
rho_l, limits inclusive on the plain distance); move test: Eq. (6); random walk: q ~ U{Q}, Eqs. (7)-(8)
(Sec. "Local Minima Trap"). The engine is in ``bacteria.py``.

Notes
-----
``RandomWalkRule.SAFE_SET`` samples q uniformly from the safe set Q as the paper writes it;
``RandomWalkRule.SINGLE_DRAW`` is the authors' code (one index from all N_b points, move only if that point is
safe, otherwise no move this iteration, reported as ``LOCAL_MINIMUM``).
"""

from __future__ import annotations

from apf_companion.planning.bacteria import BacteriaPlanner

__all__ = ["CrBapfPlanner", "CrBapfStarPlanner"]


class CrBapfPlanner(BacteriaPlanner):
    """CR-BAPF: branching repulsion of Eq. (13); no move at a local minimum."""

    name = "cr-bapf"
    branching = True


class CrBapfStarPlanner(BacteriaPlanner):
    """CR-BAPF*: CR-BAPF plus the random walk of ``PlannerParams.random_walk``."""

    name = "cr-bapf*"
    branching = True
    random_walk = True
