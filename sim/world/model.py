"""The obstacle world: vertical cylinders (point obstacles with a radius) and walls, in local NED north/east metres.

World coordinates are local NED north/east relative to the vehicle's EKF origin, which the simulator also uses
as home. Cylinders stand on the ground and reach up to ``height_m`` above it (``inf`` = any altitude); a radius of
0 is the paper's point obstacle. Walls are line segments with a thickness (a capsule around the segment) and a
height; polygons are stored as their closed chain of wall segments.

All queries are vectorised over obstacles (and over sectors for the range windows); no per-obstacle Python loops.
What a range sensor sees (``window_ranges_m``, ``ray_cast_m``) is computed in ``sensing.py``; the World's
methods of those names call it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.planning import FlyingArea, KeepOuts, PolygonNE, area_text, polygon_problem, zone_conflict
from sim.world import sensing
from sim.world.sensing import closest_point_on_segments

FloatArray = npt.NDArray[np.float64]

__all__ = ["FloatArray", "World"]


def _as_array(values: object, shape_tail: tuple[int, ...], name: str) -> FloatArray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, *shape_tail), dtype=np.float64)
    if arr.shape[1:] != shape_tail:
        msg = f"{name}: expected shape (N, {', '.join(map(str, shape_tail))}), got {arr.shape}"
        raise ConfigError(msg)
    return arr


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class World:
    """Static obstacles in local NED north/east metres.

    Attributes:
        circles_ne_m: (N, 2) cylinder centres [m].
        circle_radii_m: (N,) cylinder radii [m] (0 = point obstacle).
        circle_heights_m: (N,) cylinder top above ground [m] (inf = unbounded).
        walls_ne_m: (M, 2, 2) wall segments, ``[[n0, e0], [n1, e1]]`` [m].
        wall_thickness_m: (M,) full wall thickness [m].
        wall_heights_m: (M,) wall top above ground [m] (inf = unbounded).
        name: a label for logs and results.
        start_ne_m / goal_ne_m: optional suggested start and goal (the paper's (3, 3) and (22, 22)).
        area_ne_m: optional flying area (north_min, east_min, north_max, east_max) [m], the bounds a user would
            fence: given to bapf-nav as ``nav_area_ne_m`` by the study and ``apf-sim fly``.
        keepouts_ne_m: keep-out zones (polygons) [m], a fence's exclusion zones: bapf-nav's ``nav_keepout_ne_m``.
            No obstacle: nothing marks them, and the study's optimum does not know them.
    """

    circles_ne_m: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    circle_radii_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    circle_heights_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    walls_ne_m: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    wall_thickness_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    wall_heights_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    name: str = "empty"
    start_ne_m: tuple[float, float] | None = None
    goal_ne_m: tuple[float, float] | None = None
    area_ne_m: FlyingArea | None = None
    keepouts_ne_m: KeepOuts = ()

    def __post_init__(self) -> None:
        if self.area_ne_m is not None:
            object.__setattr__(self, "area_ne_m", _area(self.area_ne_m))
        object.__setattr__(self, "keepouts_ne_m", tuple(_keepout(z) for z in self.keepouts_ne_m))
        self._check_zones()
        circles = _as_array(self.circles_ne_m, (2,), "circles_ne_m")
        n = circles.shape[0]
        radii = np.broadcast_to(np.asarray(self.circle_radii_m, dtype=np.float64), (n,)).copy()
        heights = np.broadcast_to(np.asarray(self.circle_heights_m, dtype=np.float64), (n,)).copy()
        walls = _as_array(self.walls_ne_m, (2, 2), "walls_ne_m")
        m = walls.shape[0]
        thick = np.broadcast_to(np.asarray(self.wall_thickness_m, dtype=np.float64), (m,)).copy()
        wall_h = np.broadcast_to(np.asarray(self.wall_heights_m, dtype=np.float64), (m,)).copy()
        if not np.all(np.isfinite(circles)) or not np.all(np.isfinite(walls)):
            raise ConfigError("world: obstacle coordinates must be finite")
        if np.any(~(radii >= 0)) or np.any(~np.isfinite(radii)):
            raise ConfigError("world: circle_radii_m must be finite and >= 0")
        if np.any(~(thick >= 0)) or np.any(~np.isfinite(thick)):
            raise ConfigError("world: wall_thickness_m must be finite and >= 0")
        if np.any(~(heights > 0)) or np.any(~(wall_h > 0)):
            raise ConfigError("world: heights must be > 0 (inf = unbounded)")
        for name, arr in (
            ("circles_ne_m", circles),
            ("circle_radii_m", radii),
            ("circle_heights_m", heights),
            ("walls_ne_m", walls),
            ("wall_thickness_m", thick),
            ("wall_heights_m", wall_h),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def _check_zones(self) -> None:
        """The start and the goal lie in the flying area and in no keep-out zone (bapf-nav gives up at once on a
        goal there; ``planning.zone_conflict``, the service's rule)."""
        points = [(key, p) for key, p in (("start_ne_m", self.start_ne_m), ("goal_ne_m", self.goal_ne_m)) if p]
        if not points:
            return
        north, east = zip(*(p for _, p in points), strict=True)
        conflict = zone_conflict(self.area_ne_m, self.keepouts_ne_m, north, east)
        if conflict is None:
            return
        key, point = points[conflict.index]
        if conflict.keepout is not None or self.area_ne_m is None:
            where = "in a keep-out zone"
        else:
            where = f"outside area_ne_m = {area_text(self.area_ne_m)}"
        raise ConfigError(f"world: {key} = {[float(v) for v in point]} lies {where}")

    # ------------------------------------------------------------------------------------------- builders
    @classmethod
    def empty(cls, name: str = "empty") -> World:
        return cls(name=name)

    @classmethod
    def from_obstacles(
        cls,
        circles_ne_m: npt.ArrayLike = (),
        radii_m: npt.ArrayLike | float = 0.0,
        *,
        heights_m: npt.ArrayLike | float = math.inf,
        walls_ne_m: npt.ArrayLike = (),
        wall_thickness_m: npt.ArrayLike | float = 0.0,
        wall_heights_m: npt.ArrayLike | float = math.inf,
        name: str = "world",
        start_ne_m: tuple[float, float] | None = None,
        goal_ne_m: tuple[float, float] | None = None,
    ) -> World:
        """A world from plain sequences; scalars broadcast over obstacles."""
        return cls(
            circles_ne_m=np.asarray(circles_ne_m, dtype=np.float64),
            circle_radii_m=np.asarray(radii_m, dtype=np.float64),
            circle_heights_m=np.asarray(heights_m, dtype=np.float64),
            walls_ne_m=np.asarray(walls_ne_m, dtype=np.float64),
            wall_thickness_m=np.asarray(wall_thickness_m, dtype=np.float64),
            wall_heights_m=np.asarray(wall_heights_m, dtype=np.float64),
            name=name,
            start_ne_m=start_ne_m,
            goal_ne_m=goal_ne_m,
        )

    def merged(self, other: World, name: str | None = None) -> World:
        """This world plus ``other``'s obstacles (start/goal from self, else other)."""
        return World(
            circles_ne_m=np.concatenate([self.circles_ne_m, other.circles_ne_m]),
            circle_radii_m=np.concatenate([self.circle_radii_m, other.circle_radii_m]),
            circle_heights_m=np.concatenate([self.circle_heights_m, other.circle_heights_m]),
            walls_ne_m=np.concatenate([self.walls_ne_m, other.walls_ne_m]),
            wall_thickness_m=np.concatenate([self.wall_thickness_m, other.wall_thickness_m]),
            wall_heights_m=np.concatenate([self.wall_heights_m, other.wall_heights_m]),
            name=name or self.name,
            start_ne_m=self.start_ne_m or other.start_ne_m,
            goal_ne_m=self.goal_ne_m or other.goal_ne_m,
            area_ne_m=self.area_ne_m or other.area_ne_m,
            keepouts_ne_m=self.keepouts_ne_m + other.keepouts_ne_m,
        )

    @staticmethod
    def polygon_segments(points_ne_m: Sequence[Sequence[float]], *, closed: bool = True) -> FloatArray:
        """The (K, 2, 2) wall segments of a polyline (closed: last point joins the first)."""
        pts = np.asarray(points_ne_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
            msg = f"polygon: points_ne_m must be a list of >= 2 [north, east] pairs, got shape {pts.shape}"
            raise ConfigError(msg)
        ends = np.roll(pts, -1, axis=0) if closed else pts[1:]
        starts = pts if closed else pts[:-1]
        return np.stack([starts, ends], axis=1)

    # ------------------------------------------------------------------------------------------- queries
    @property
    def n_circles(self) -> int:
        return int(self.circles_ne_m.shape[0])

    @property
    def n_walls(self) -> int:
        return int(self.walls_ne_m.shape[0])

    @property
    def n_obstacles(self) -> int:
        """Obstacle ids: circles 0..N-1, then walls N..N+M-1."""
        return self.n_circles + self.n_walls

    def surface_distances_m(self, pos_ne_m: npt.ArrayLike, alt_m: float = 0.0) -> FloatArray:
        """Distance from one point to each obstacle's surface [m] (circles then walls; negative inside).

        Obstacles whose top is below ``alt_m`` (height above ground) are out of reach: +inf.
        """
        p = np.asarray(pos_ne_m, dtype=np.float64).reshape(2)
        parts = []
        if self.n_circles:
            rel = self.circles_ne_m - p
            d_c = np.hypot(rel[:, 0], rel[:, 1]) - self.circle_radii_m
            parts.append(np.where(self.circle_heights_m >= alt_m, d_c, np.inf))
        if self.n_walls:
            d_w = _point_segment_distance(p, self.walls_ne_m) - 0.5 * self.wall_thickness_m
            parts.append(np.where(self.wall_heights_m >= alt_m, d_w, np.inf))
        if not parts:
            return np.zeros(0)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def clearance_m(self, pos_ne_m: npt.ArrayLike, alt_m: float = 0.0) -> float:
        """Distance from a point to the nearest obstacle surface [m] (inf in an empty world)."""
        d = self.surface_distances_m(pos_ne_m, alt_m)
        return float(d.min()) if d.size else math.inf

    def nearest_obstacle(self, pos_ne_m: npt.ArrayLike, alt_m: float = 0.0) -> tuple[int, float]:
        """(obstacle id, surface distance [m]) of the nearest obstacle; (-1, inf) when there is none."""
        d = self.surface_distances_m(pos_ne_m, alt_m)
        if d.size == 0 or not np.isfinite(d.min()):
            return -1, math.inf
        i = int(np.argmin(d))
        return i, float(d[i])

    def nearest_points_ne_m(self, pos_ne_m: npt.ArrayLike, alt_m: float = 0.0) -> tuple[FloatArray, FloatArray]:
        """Per obstacle: the nearest surface point (K, 2) and its distance (K,) [m]; unreachable ones get inf."""
        p = np.asarray(pos_ne_m, dtype=np.float64).reshape(2)
        rel = self.circles_ne_m - p
        dist_c = np.hypot(rel[:, 0], rel[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(dist_c[:, None] > 0, rel / dist_c[:, None], 0.0)
        pts_c = self.circles_ne_m - unit * self.circle_radii_m[:, None]
        d_c = np.where(self.circle_heights_m >= alt_m, np.maximum(dist_c - self.circle_radii_m, 0.0), np.inf)
        foot = closest_point_on_segments(p, self.walls_ne_m)
        rel_w = foot - p
        dist_w = np.hypot(rel_w[:, 0], rel_w[:, 1])
        half = 0.5 * self.wall_thickness_m
        with np.errstate(invalid="ignore", divide="ignore"):
            unit_w = np.where(dist_w[:, None] > 0, rel_w / dist_w[:, None], 0.0)
        pts_w = foot - unit_w * half[:, None]
        d_w = np.where(self.wall_heights_m >= alt_m, np.maximum(dist_w - half, 0.0), np.inf)
        return np.concatenate([pts_c, pts_w]), np.concatenate([d_c, d_w])

    def window_ranges_m(
        self,
        pos_ne_m: npt.ArrayLike,
        centres_rad: npt.ArrayLike,
        half_width_rad: float,
        *,
        alt_m: float = 0.0,
    ) -> FloatArray:
        """Exact range to the nearest obstacle surface inside each angular window, seen from ``pos_ne_m``.

        Args:
            pos_ne_m: the sensor position (north, east) [m].
            centres_rad: (S,) window centre bearings, clockwise from north [rad].
            half_width_rad: half the window width [rad] (< pi/2).
            alt_m: the sensor's height above ground [m]; obstacles whose top is lower are not seen.

        Returns:
            (S,) the minimum distance over every ray in each window to any obstacle surface [m]; inf if none.
            A sensor inside an obstacle reads 0 in every window.
        """
        return sensing.window_ranges_m(self, pos_ne_m, centres_rad, half_width_rad, alt_m=alt_m)

    def ray_cast_m(self, pos_ne_m: npt.ArrayLike, bearings_rad: npt.ArrayLike, *, alt_m: float = 0.0) -> FloatArray:
        """Range along single rays (bearing clockwise from north) to the first obstacle surface [m]; inf if none.

        Walls are hit at their centre line (thickness ignored here); circles at their surface.
        """
        return sensing.ray_cast_m(self, pos_ne_m, bearings_rad, alt_m=alt_m)

    def describe(self) -> dict[str, object]:
        """A JSON-ready description (for results and plots)."""
        return {
            "name": self.name,
            "circles_ne_m": self.circles_ne_m.tolist(),
            "circle_radii_m": self.circle_radii_m.tolist(),
            "circle_heights_m": [h if math.isfinite(h) else None for h in self.circle_heights_m.tolist()],
            "walls_ne_m": self.walls_ne_m.tolist(),
            "wall_thickness_m": self.wall_thickness_m.tolist(),
            "wall_heights_m": [h if math.isfinite(h) else None for h in self.wall_heights_m.tolist()],
            "start_ne_m": list(self.start_ne_m) if self.start_ne_m else None,
            "goal_ne_m": list(self.goal_ne_m) if self.goal_ne_m else None,
            "area_ne_m": _area_json(self.area_ne_m),
            "keepouts_ne_m": [[list(v) for v in zone] for zone in self.keepouts_ne_m],
        }


def _area(value: Sequence[Any]) -> FlyingArea:
    """A flying area [m], checked: a rectangle (north_min, east_min, north_max, east_max), finite, min < max; or a
    polygon ((north, east), ...) of finite vertices whose edges do not cross."""
    if value and all(isinstance(v, Sequence) for v in value):
        polygon = tuple((float(v[0]), float(v[1])) for v in value if len(v) == 2)
        problem = None if len(polygon) == len(value) and all(map(math.isfinite, sum(polygon, ()))) else "finite pairs"
        problem = problem or polygon_problem(polygon)
        if problem is not None:
            msg = f"world: a polygonal area_ne_m must be {problem} [[north, east], ...]: {value!r}"
            raise ConfigError(msg)
        return polygon
    area = tuple(float(v) for v in value)
    if len(area) != 4 or not all(math.isfinite(v) for v in area) or not (area[0] < area[2] and area[1] < area[3]):
        msg = f"world: area_ne_m must be finite [[north_min, east_min], [north_max, east_max]], min < max: {value!r}"
        raise ConfigError(msg)
    return area[0], area[1], area[2], area[3]


def _keepout(value: Sequence[Any]) -> PolygonNE:
    """A keep-out zone: a polygon of finite (north, east) vertices whose edges do not cross [m]."""
    polygon = tuple((float(v[0]), float(v[1])) for v in value if len(v) == 2)
    finite = len(polygon) == len(value) and all(map(math.isfinite, sum(polygon, ())))
    problem = polygon_problem(polygon) if finite else "finite pairs"
    if problem is not None:
        msg = f"world: a keep-out zone must be {problem} [[north, east], ...]: {value!r}"
        raise ConfigError(msg)
    return polygon


def _area_json(area: FlyingArea | None) -> list[Any] | None:
    """The area as JSON: four numbers (a rectangle) or a list of [north, east] pairs (a polygon)."""
    if area is None:
        return None
    return [list(v) if isinstance(v, tuple) else v for v in area]


def _point_segment_distance(p: FloatArray, segs: FloatArray) -> FloatArray:
    foot = closest_point_on_segments(p, segs)
    return np.asarray(np.hypot(foot[:, 0] - p[0], foot[:, 1] - p[1]), dtype=np.float64)
