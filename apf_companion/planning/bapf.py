"""BAPF: the bacteria-point APF of Ahmad et al. 2020, as described in Diab et al. 2023, Sec. "BAPF".

Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered Environments",
IEEE Aerospace 2023, DOI 10.1109/AERO55745.2023.10115857. Potentials: Eqs. (1)-(5); move test: Eq. (6);
search order: Fig. 3 (first passing point in order of increasing target distance). The engine is in
``bacteria.py``.
"""

from __future__ import annotations

from apf_companion.planning.bacteria import BacteriaPlanner

__all__ = ["BapfPlanner"]


class BapfPlanner(BacteriaPlanner):
    """BAPF: repulsion of Eq. (2) from every known obstacle; no move at a local minimum."""

    name = "bapf"
