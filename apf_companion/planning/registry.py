"""Planners by name: ``get_planner("cr-bapf*", params)`` or ``get_planner(PlannerName.BAPF_NAV, params)``."""

from __future__ import annotations

import enum

from apf_companion.errors import ConfigError
from apf_companion.planning.abapf import AbapfPlanner
from apf_companion.planning.bapf import BapfPlanner
from apf_companion.planning.bapfnav import BapfNavPlanner
from apf_companion.planning.base import Planner
from apf_companion.planning.bendyruler import BendyRulerPlanner
from apf_companion.planning.capf import CapfPlanner
from apf_companion.planning.crbapf import CrBapfPlanner, CrBapfStarPlanner
from apf_companion.planning.params import PlannerParams

__all__ = ["ALL_PLANNER_NAMES", "PAPER_PLANNER_NAMES", "PLANNER_NAMES", "PlannerName", "get_planner"]


class PlannerName(enum.StrEnum):
    """Every planner's name, defined once (a plain string such as ``"cr-bapf*"`` works wherever one is used)."""

    CAPF = "capf"
    BAPF = "bapf"
    A_BAPF = "a-bapf"
    CR_BAPF = "cr-bapf"
    CR_BAPF_STAR = "cr-bapf*"
    #: The product planner (the service's default).
    BAPF_NAV = "bapf-nav"
    #: ArduPilot-BendyRuler-style comparison baseline.
    BENDYRULER = "bendyruler"


_PLANNERS: dict[str, type[Planner]] = {
    cls.name: cls
    for cls in (
        CapfPlanner,
        BapfPlanner,
        AbapfPlanner,
        CrBapfPlanner,
        CrBapfStarPlanner,
        BapfNavPlanner,
        BendyRulerPlanner,
    )
}
#: The five planners of the paper, in the paper's order.
PAPER_PLANNER_NAMES: tuple[str, ...] = ("capf", "bapf", "a-bapf", "cr-bapf", "cr-bapf*")
PLANNER_NAMES = PAPER_PLANNER_NAMES
#: Every registered planner: the paper's five, then the product planner and the baseline.
ALL_PLANNER_NAMES: tuple[str, ...] = tuple(str(n) for n in PlannerName)
#: The planner the service and ``apf-sim fly`` use unless told otherwise.
DEFAULT_PLANNER = PlannerName.BAPF_NAV


def get_planner(name: str, params: PlannerParams | None = None) -> Planner:
    """The planner called ``name`` (one of ``ALL_PLANNER_NAMES``), with ``params`` (default ``PlannerParams()``)."""
    try:
        cls = _PLANNERS[str(name)]
    except (KeyError, TypeError):
        raise ConfigError(f"planner name {name!r} is unknown; allowed: {', '.join(ALL_PLANNER_NAMES)}") from None
    return cls(params if params is not None else PlannerParams())
