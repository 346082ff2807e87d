"""Planners by name: ``get_planner("cr-bapf*", params)``."""

from __future__ import annotations

from apf_companion.errors import ConfigError
from apf_companion.planning.abapf import AbapfPlanner
from apf_companion.planning.bapf import BapfPlanner
from apf_companion.planning.base import Planner
from apf_companion.planning.capf import CapfPlanner
from apf_companion.planning.crbapf import CrBapfPlanner, CrBapfStarPlanner
from apf_companion.planning.params import PlannerParams

__all__ = ["PLANNER_NAMES", "get_planner"]

_PLANNERS: dict[str, type[Planner]] = {
    cls.name: cls for cls in (CapfPlanner, BapfPlanner, AbapfPlanner, CrBapfPlanner, CrBapfStarPlanner)
}
#: The five planners of the paper, in the paper's order.
PLANNER_NAMES: tuple[str, ...] = ("capf", "bapf", "a-bapf", "cr-bapf", "cr-bapf*")


def get_planner(name: str, params: PlannerParams | None = None) -> Planner:
    """The planner called ``name`` (one of ``PLANNER_NAMES``), with ``params`` (default ``PlannerParams()``)."""
    try:
        cls = _PLANNERS[name]
    except (KeyError, TypeError):
        raise ConfigError(f"planner name {name!r} is unknown; allowed: {', '.join(PLANNER_NAMES)}") from None
    return cls(params if params is not None else PlannerParams())
