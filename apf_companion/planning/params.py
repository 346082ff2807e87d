"""Planner parameters: one frozen dataclass whose defaults are the paper's Table I values.

Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered Environments",
IEEE Aerospace 2023, DOI 10.1109/AERO55745.2023.10115857. Where the paper is silent, the project's decisions in
``docs/paper/notes.md`` apply; every rule that differs between the two presets is a named field, not a hidden branch.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from apf_companion.errors import ConfigError
from apf_companion.planning.area import FlyingArea, KeepOuts, PolygonNE, area_bounds, polygon_problem

__all__ = ["AbapfRule", "AbapfSearch", "PlannerParams", "Preset", "RandomWalkRule"]


class AbapfRule(enum.Enum):
    """How A-BAPF picks mu_o,k for a bacteria point (Eq. (11))."""

    #: The exact argmin of Eq. (11). J_k(mu) is strictly decreasing in mu, so this is mu_max whenever the
    #: agent knows an obstacle (mu_min when it knows none: J_k is then constant and the first minimum is taken).
    EXACT = "exact"
    #: The rule that reproduces the paper's mu_o,k figure (float64 ties in MATLAB's ``min``): the smallest
    #: integer mu whose total repulsion is at most 2^-53 times |J_t(r_b,k)|, evaluated in logs.
    PAPER = "paper"


class AbapfSearch(enum.Enum):
    """How the mu_o,k search of Eq. (11) is carried out over [mu_min, mu_max]."""

    #: The integer grid mu_min, mu_min + 1, ..., mu_max (first minimum, as MATLAB's ``min``).
    GRID = "grid"
    #: Golden-section search on the continuous interval, finished on the integer grid.
    GOLDEN = "golden"


class Preset(enum.StrEnum):
    """Named parameter sets (``PlannerParams.from_preset``); the names are defined here once."""

    #: ``PlannerParams()``: the paper's Table I values.
    DEFAULT = "default"
    #: The paper's text (``PlannerParams.paper()``).
    PAPER = "paper"
    #: The authors' published code (``PlannerParams.reference()``).
    REFERENCE = "reference"


class RandomWalkRule(enum.Enum):
    """CR-BAPF* escape move when no bacteria point passes Eq. (6)."""

    #: The paper's text, Eqs. (7)-(8): q ~ U{Q}, uniform over the safe points (at least rho_l from every known
    #: obstacle); an empty Q is a local minimum.
    SAFE_SET = "safe-set"
    #: The authors' code: one index drawn uniformly from all N_b points; the agent moves only if that point is
    #: safe, otherwise the iteration passes without a move (reported as a local minimum).
    SINGLE_DRAW = "single-draw"


#: Cells a side of a flying area's fixed grid (``nav_area_ne_m``), at most. A field is one Dijkstra search over
#: every cell, in the service's cycle: 256 x 256 cells took 22.6 ms on the 2-core development VM (384 x 384: 54 ms,
#: more than a 20 Hz cycle), so a larger area is planned on the grid that moves with the agent, its cells outside
#: the area closed (docs/planner.md, "A flying area").
MAX_AREA_CELLS = 256
#: Vertices of a polygonal flying area or keep-out zone, at most: the line-of-sight test crosses every edge each step.
MAX_AREA_VERTICES = 64
#: Keep-out zones, at most (``nav_keepout_ne_m``): each costs a point-in-polygon pass per field of a moving grid.
MAX_KEEPOUTS = 16


def _fail(name: str, value: object, allowed: str) -> ConfigError:
    return ConfigError(f"PlannerParams.{name} = {value!r} is invalid; allowed: {allowed}")


def _finite(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise _fail(name, value, "a finite real number")
    return float(value)


@dataclass(frozen=True, slots=True, kw_only=True)
class PlannerParams:
    """Parameters of every planner; defaults are the paper's Table I values (2D).

    Attributes
    ----------
    alpha_t : target potential gain alpha_t of Eq. (1), > 0.
    mu_t_per_m2 : target decay mu_t of Eq. (1) [1/m^2], > 0.
    alpha_o : obstacle potential gain alpha_o of Eqs. (2), (10), (13), > 0.
    mu_o_per_m2 : obstacle decay mu_o of Eqs. (2), (13) [1/m^2], > 0.
    rho_l_m : lower (safety) radius of Eq. (13) [m], 0 <= rho_l_m < rho_u_m.
    rho_u_m : upper radius of Eq. (13) [m]; obstacles farther away do not repel.
    step_m : movement step, the bacteria ring/sphere radius [m], > 0.
    n_bacteria : number of bacteria points N_b, >= 3 (2D) or >= 4 (3D).
    mu_min, mu_max : the integer search interval [mu_min : mu_max] of Eq. (11) [1/m^2], 1 <= mu_min <= mu_max.
    abapf_rule, abapf_search : A-BAPF rule and search method (see the enums).
    random_walk : CR-BAPF* escape rule.
    agent_repulsion : include the agent's own repulsion J_o(r) in J_a (Eq. (4)). False reproduces the
        authors' code, where J_o(r) is always 0 (docs/paper/notes.md), so greedy moves only decrease the target
        distance.
    capf_k_att : CAPF attractive gain [1/m^2-ish, potential per m^2], > 0.
    capf_eta : CAPF FIRAS repulsion gain, >= 0.
    capf_rho_0_m : CAPF repulsion influence distance [m], > 0.
    dim : 2 (ring of bacteria points) or 3 (sphere).

    The product planners (``bapf-nav``, ``bendyruler``; the paper's five ignore these fields):

    vehicle_radius_m : radius of the vehicle, the collision distance [m], > 0.
    safety_margin_m : clearance kept beyond the radius [m], >= 0.
    noise_std_m : known position / actuation noise, standard deviation per axis [m], >= 0.
    noise_k : the noise margin is noise_k * noise_std_m [m], >= 0.
    nav_clearance_gain_m : bapf-nav: gain of the clearance term of the score, Eq. (2) form, in metres of path, >= 0.
    nav_clearance_decay_per_m2 : bapf-nav: decay of that term (mu_o of Eq. (2) at product scale) [1/m^2], > 0.
    nav_lookahead_m : bapf-nav: length of the look-ahead probe from each candidate towards the goal [m], >= 0
        (0 = off).
    nav_lookahead_penalty_m : bapf-nav: score penalty of a candidate whose look-ahead probe is blocked [m], >= 0.
    nav_hold_angle_deg : bapf-nav: a turn of more than this from the previous move is taken only when it gains
        ``nav_hold_ratio`` times what the best candidate within the angle gains [deg], in [0, 180].
    nav_hold_ratio : bapf-nav: see ``nav_hold_angle_deg``, >= 1.
    nav_cell_m : bapf-nav: cell size of the navigation grid [m], > 0.
    nav_grid_m : bapf-nav: side of the square navigation grid [m], >= 8 nav_cell_m and at most 4096 cells a side.
    nav_replan_steps : bapf-nav: recompute the navigation potential every this many escape steps (new
        obstacles), >= 1.
    nav_sight_m : bapf-nav: the line of sight tested towards the goal [m], >= 0 (0 = off). While a remembered
        surface (a wall or trunk: a point with two known neighbours within 0.45 m), inflated by the clearance,
        blocks the straight line within this distance, the agent descends the geodesic potential (ESCAPE) instead
        of the straight-line one, before a concave obstacle traps it.
    nav_sight_points_m : bapf-nav: any remembered point, a lone one too, blocks the line of sight within this
        distance [m], >= 0 (0 = only surfaces block it; at most ``nav_sight_m`` counts): clusters of point obstacles
        are passed on the geodesic potential once near.
    nav_seen_m : bapf-nav: edge cells of the navigation grid within this distance of where the agent has been
        are not exits into unknown space (it has looked there) [m], >= 0 (0 = every edge cell is an exit).
    nav_patience_steps : bapf-nav: give up (STUCK) after this many steps without a new closest approach to the
        target, >= 1.
    nav_area_ne_m : bapf-nav: the flying area in local NED [m], or None (default): a rectangle (north_min,
        east_min, north_max, east_max) or a polygon ((north, east), ...), which may be concave. When set, the
        navigation grid covers the whole area (its bounds) instead of ``nav_grid_m`` around the agent: its cells
        outside the area are blocked and its edge is no exit into unknown space, so an escape searches every way
        the area holds, as ArduPilot's Dijkstra planner plans within its fence
        (libraries/AC_Avoidance/AP_OADijkstra.h, "path planning around polygon fence"). A target outside the
        area has no way: the agent gives up at once (STUCK). A straight line to the target that leaves a
        polygon starts an escape, as an obstacle on it does (``area.leaves_area``). The bounds are at least 8
        cells of ``nav_cell_m`` a side. An area wider than ``MAX_AREA_CELLS`` = 256 cells (76.8 m at 0.3 m
        cells; a field is a search over every cell, in the service's cycle) is planned on the ``nav_grid_m`` grid
        that moves with the agent instead, its cells outside the area closed and its edge cells inside the area
        exits into unknown space, as without an area.
    nav_keepout_ne_m : bapf-nav: keep-out zones, polygons ((north, east), ...) in local NED [m] the vehicle must not
        enter (a fence's exclusion zones), with or without a flying area; at most ``MAX_KEEPOUTS`` = 16 of 3 to 64
        vertices. Their cells are blocked in every field, a target in one gives up at once, and a straight line
        that meets one blocks the line of sight (``area.meets_keepout``).
    br_lookahead_m : bendyruler: probe length OA_BR_LOOKAHEAD [m], > 0.
    br_margin_max_m : bendyruler: clearance OA_MARGIN_MAX that makes a direction "sufficiently open" [m], > 0.
    br_cont_ratio : bendyruler: OA_BR_CONT_RATIO, >= 1.
    br_cont_angle_deg : bendyruler: OA_BR_CONT_ANGLE [deg], in [0, 180].
    """

    alpha_t: float = 1e4
    mu_t_per_m2: float = 1.0
    alpha_o: float = 1.0
    mu_o_per_m2: float = 1000.0
    rho_l_m: float = 0.4
    rho_u_m: float = 4.5
    step_m: float = 0.4
    n_bacteria: int = 60
    mu_min: int = 1
    mu_max: int = 1000
    abapf_rule: AbapfRule = AbapfRule.EXACT
    abapf_search: AbapfSearch = AbapfSearch.GRID
    random_walk: RandomWalkRule = RandomWalkRule.SAFE_SET
    agent_repulsion: bool = True
    capf_k_att: float = 1.0
    capf_eta: float = 100.0
    capf_rho_0_m: float = 3.0
    dim: int = 2
    vehicle_radius_m: float = 0.25
    safety_margin_m: float = 0.1
    noise_std_m: float = 0.1
    noise_k: float = 2.5
    nav_clearance_gain_m: float = 0.3
    nav_clearance_decay_per_m2: float = 4.0
    nav_lookahead_m: float = 1.2
    nav_lookahead_penalty_m: float = 0.2
    nav_hold_angle_deg: float = 75.0
    nav_hold_ratio: float = 1.5
    nav_cell_m: float = 0.3
    nav_grid_m: float = 16.0
    nav_replan_steps: int = 25
    nav_sight_m: float = 8.0
    nav_sight_points_m: float = 2.0
    nav_seen_m: float = 4.0
    nav_patience_steps: int = 300
    nav_area_ne_m: FlyingArea | None = None
    nav_keepout_ne_m: KeepOuts = ()
    br_lookahead_m: float = 1.2
    br_margin_max_m: float = 0.6
    br_cont_ratio: float = 1.5
    br_cont_angle_deg: float = 75.0

    @property
    def clearance_m(self) -> float:
        """The clearance the product planners keep: vehicle radius + safety margin + noise_k * noise_std_m [m]."""
        return self.vehicle_radius_m + self.safety_margin_m + self.noise_k * self.noise_std_m

    def __post_init__(self) -> None:
        positive = ("alpha_t", "mu_t_per_m2", "alpha_o", "mu_o_per_m2", "step_m", "capf_k_att", "capf_rho_0_m")
        for name in positive:
            if _finite(name, getattr(self, name)) <= 0.0:
                raise _fail(name, getattr(self, name), "a finite number > 0")
        if _finite("capf_eta", self.capf_eta) < 0.0:
            raise _fail("capf_eta", self.capf_eta, "a finite number >= 0")
        rho_l = _finite("rho_l_m", self.rho_l_m)
        rho_u = _finite("rho_u_m", self.rho_u_m)
        if rho_l < 0.0:
            raise _fail("rho_l_m", self.rho_l_m, "a finite number in [0, rho_u_m)")
        if rho_u <= rho_l:
            raise _fail("rho_u_m", self.rho_u_m, f"a finite number > rho_l_m = {self.rho_l_m!r}")
        for name in ("n_bacteria", "mu_min", "mu_max", "dim"):
            value: Any = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise _fail(name, value, "an int")
        if self.dim not in (2, 3):
            raise _fail("dim", self.dim, "2 or 3")
        min_bacteria = 3 if self.dim == 2 else 4
        if self.n_bacteria < min_bacteria:
            raise _fail("n_bacteria", self.n_bacteria, f"an int >= {min_bacteria} for dim = {self.dim}")
        if self.mu_min < 1:
            raise _fail("mu_min", self.mu_min, "an int >= 1")
        if self.mu_max < self.mu_min:
            raise _fail("mu_max", self.mu_max, f"an int >= mu_min = {self.mu_min}")
        enums: tuple[tuple[str, type[enum.Enum]], ...] = (
            ("abapf_rule", AbapfRule),
            ("abapf_search", AbapfSearch),
            ("random_walk", RandomWalkRule),
        )
        for name, kind in enums:
            if not isinstance(getattr(self, name), kind):
                allowed = ", ".join(f"{kind.__name__}.{m.name}" for m in kind)
                raise _fail(name, getattr(self, name), allowed)
        if not isinstance(self.agent_repulsion, bool):
            raise _fail("agent_repulsion", self.agent_repulsion, "True or False")
        self._check_product_fields()

    def _check_product_fields(self) -> None:
        """The fields of the product planners (bapf-nav, bendyruler)."""
        for name in (
            "vehicle_radius_m",
            "nav_clearance_decay_per_m2",
            "nav_cell_m",
            "br_lookahead_m",
            "br_margin_max_m",
        ):
            if _finite(name, getattr(self, name)) <= 0.0:
                raise _fail(name, getattr(self, name), "a finite number > 0")
        non_negative = ("safety_margin_m", "noise_std_m", "noise_k", "nav_clearance_gain_m", "nav_lookahead_m")
        for name in (*non_negative, "nav_lookahead_penalty_m", "nav_sight_m", "nav_sight_points_m", "nav_seen_m"):
            if _finite(name, getattr(self, name)) < 0.0:
                raise _fail(name, getattr(self, name), "a finite number >= 0")
        for name in ("nav_hold_angle_deg", "br_cont_angle_deg"):
            if not 0.0 <= _finite(name, getattr(self, name)) <= 180.0:
                raise _fail(name, getattr(self, name), "a finite number in [0, 180]")
        for name in ("nav_hold_ratio", "br_cont_ratio"):
            if _finite(name, getattr(self, name)) < 1.0:
                raise _fail(name, getattr(self, name), "a finite number >= 1")
        cells = _finite("nav_grid_m", self.nav_grid_m) / self.nav_cell_m
        if not 8.0 <= cells <= 4096.0:
            raise _fail("nav_grid_m", self.nav_grid_m, f"a side of 8 to 4096 cells of nav_cell_m = {self.nav_cell_m!r}")
        for name in ("nav_replan_steps", "nav_patience_steps"):
            value: Any = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise _fail(name, value, "an int >= 1")
        self._check_area()
        self._check_keepouts()

    def _check_area(self) -> None:
        """``nav_area_ne_m``: None, a rectangle (four finite numbers, min < max) or a polygon (3 to
        ``MAX_AREA_VERTICES`` finite [north, east] pairs, edges that do not cross), at least 8 cells a side (its
        bounds); kept as a tuple of floats or of pairs (a config file gives lists)."""
        area: Any = self.nav_area_ne_m
        if area is None:
            return
        allowed = (
            f"None, [north_min, east_min, north_max, east_max] (min < max) or [[north, east], ...] (3 to "
            f"{MAX_AREA_VERTICES} vertices, edges that do not cross) [m], at least 8 cells of nav_cell_m a side"
        )
        if isinstance(area, str | bytes) or not isinstance(area, tuple | list) or not area:
            raise _fail("nav_area_ne_m", area, allowed)
        value: FlyingArea
        if all(isinstance(v, tuple | list) for v in area):
            if not 3 <= len(area) <= MAX_AREA_VERTICES or any(len(v) != 2 for v in area):
                raise _fail("nav_area_ne_m", area, allowed)
            value = tuple((_finite("nav_area_ne_m", v[0]), _finite("nav_area_ne_m", v[1])) for v in area)
            if polygon_problem(value) is not None:
                raise _fail("nav_area_ne_m", area, allowed)
        elif len(area) == 4:
            n_min, e_min, n_max, e_max = (_finite("nav_area_ne_m", v) for v in area)
            value = (n_min, e_min, n_max, e_max)
        else:
            raise _fail("nav_area_ne_m", area, allowed)
        bounds = area_bounds(value)
        sides = (bounds[2] - bounds[0], bounds[3] - bounds[1])
        if not all(8.0 * self.nav_cell_m <= side for side in sides):
            raise _fail("nav_area_ne_m", area, allowed)
        object.__setattr__(self, "nav_area_ne_m", value)

    def _check_keepouts(self) -> None:
        """``nav_keepout_ne_m``: up to ``MAX_KEEPOUTS`` polygons of 3 to ``MAX_AREA_VERTICES`` finite [north, east]
        pairs whose edges do not cross; kept as a tuple of tuples of pairs (a config file gives lists)."""
        zones: Any = self.nav_keepout_ne_m
        allowed = (
            f"[[[north, east], ...], ...]: up to {MAX_KEEPOUTS} polygons of 3 to {MAX_AREA_VERTICES} vertices [m] "
            "whose edges do not cross"
        )
        if isinstance(zones, str | bytes) or not isinstance(zones, tuple | list) or len(zones) > MAX_KEEPOUTS:
            raise _fail("nav_keepout_ne_m", zones, allowed)
        kept: list[PolygonNE] = []
        for zone in zones:
            if (
                isinstance(zone, str | bytes)
                or not isinstance(zone, tuple | list)
                or not 3 <= len(zone) <= MAX_AREA_VERTICES
            ):
                raise _fail("nav_keepout_ne_m", zones, allowed)
            if not all(isinstance(v, tuple | list) and len(v) == 2 for v in zone):
                raise _fail("nav_keepout_ne_m", zones, allowed)
            polygon = tuple((_finite("nav_keepout_ne_m", v[0]), _finite("nav_keepout_ne_m", v[1])) for v in zone)
            if polygon_problem(polygon) is not None:
                raise _fail("nav_keepout_ne_m", zones, allowed)
            kept.append(polygon)
        object.__setattr__(self, "nav_keepout_ne_m", tuple(kept))

    @classmethod
    def paper(cls, **overrides: Any) -> PlannerParams:
        """The paper's text: Table I values, J_a with its repulsion, random walk over the safe set."""
        return dataclasses.replace(cls(), **overrides)

    @classmethod
    def from_preset(cls, preset: str) -> PlannerParams:
        """The parameters of ``preset`` (a ``Preset`` or its name); ``ConfigError`` for an unknown name."""
        makers: dict[Preset, Callable[[], PlannerParams]] = {
            Preset.DEFAULT: cls,
            Preset.PAPER: cls.paper,
            Preset.REFERENCE: cls.reference,
        }
        try:
            make = makers[Preset(preset)]
        except ValueError:
            msg = f"preset {preset!r} is unknown; allowed: {', '.join(Preset)}"
            raise ConfigError(msg) from None
        return make()

    @classmethod
    def reference(cls, **overrides: Any) -> PlannerParams:
        """The authors' published MATLAB code (docs/paper/notes.md): alpha_t = 1e5, J_o(r) = 0, single-draw walk."""
        base = cls(alpha_t=1e5, agent_repulsion=False, random_walk=RandomWalkRule.SINGLE_DRAW)
        return dataclasses.replace(base, **overrides)
