"""World files: a small documented TOML format (examples in ``sim/world/examples/``).

Format (all coordinates local NED north/east metres relative to home = the EKF origin; every key optional)::

    name = "forest"                     # a label
    start_ne_m = [3.0, 3.0]             # suggested start (north, east)
    goal_ne_m = [22.0, 22.0]            # suggested goal
    area_ne_m = [[0.0, 0.0], [25.0, 25.0]]  # the flying area (south-west, north-east corners), as a user would
                                        # fence it: bapf-nav plans over all of it (PlannerParams.nav_area_ne_m);
                                        # three or more pairs are a polygon's vertices (an L-shaped yard)

    [[cylinder]]                        # a vertical cylinder standing on the ground (a tree, a pole)
    ne_m = [8.0, 9.5]                   # centre
    radius_m = 0.3                      # default 0 (a point obstacle, as in the paper)
    height_m = 12.0                     # top above ground; default: unbounded

    [[wall]]                            # a straight wall (a capsule around the segment)
    from_ne_m = [0.0, 10.0]
    to_ne_m = [20.0, 10.0]
    thickness_m = 0.2                   # default 0
    height_m = 5.0                      # default: unbounded

    [[polygon]]                         # a closed outline, stored as walls between consecutive points
    points_ne_m = [[5, 5], [5, 8], [8, 8]]
    closed = true                       # default true; false = an open polyline
    thickness_m = 0.0
    height_m = 5.0

    [[keepout]]                         # a keep-out zone (a fence's exclusion zone): no obstacle, nothing marks it;
    points_ne_m = [[2, 12], [4, 12], [4, 14]]  # bapf-nav does not enter it (PlannerParams.nav_keepout_ne_m)

    [random_field]                      # optionally add the paper's random points (sim/world/field.py)
    preset = "reference"                # or "paper"
    obstacles = 40                      # or "low" / "mid" / "high"
    seed = 1
    radius_m = 0.0

Unknown keys are errors (a typo must not silently drop an obstacle).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from apf_companion.errors import ConfigError
from apf_companion.planning import FlyingArea
from sim.world.field import paper_field
from sim.world.model import World

__all__ = ["EXAMPLES_DIR", "bundled_world_names", "example_world_path", "load_world", "world_from_mapping"]

EXAMPLES_DIR = Path(__file__).parent / "examples"

_TOP_KEYS = {
    "name",
    "description",
    "start_ne_m",
    "goal_ne_m",
    "area_ne_m",
    "cylinder",
    "wall",
    "polygon",
    "keepout",
    "random_field",
}
_KEYS = {
    "cylinder": {"ne_m", "radius_m", "height_m"},
    "wall": {"from_ne_m", "to_ne_m", "thickness_m", "height_m"},
    "polygon": {"points_ne_m", "closed", "thickness_m", "height_m"},
    "keepout": {"points_ne_m"},
    "random_field": {"preset", "obstacles", "seed", "radius_m"},
}


def bundled_world_names() -> list[str]:
    """The bundled example worlds by name (the ``*.toml`` stems in ``sim/world/examples/``), sorted."""
    return sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml"))


def example_world_path(name: str) -> Path:
    """The path of a bundled example world by name (the ``*.toml`` stems in ``sim/world/examples/``)."""
    path = EXAMPLES_DIR / f"{name}.toml"
    if not path.is_file():
        msg = f"no example world {name!r}; bundled: {bundled_world_names()}"
        raise ConfigError(msg)
    return path


def load_world(path: Path | str) -> World:
    """Load a TOML world file. A bare name (no suffix, not a file) loads a bundled example."""
    p = Path(path)
    if not p.exists() and p.suffix == "" and len(p.parts) == 1:
        p = example_world_path(str(path))
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as err:
        msg = f"cannot read world file {p}: {err}"
        raise ConfigError(msg) from err
    except tomllib.TOMLDecodeError as err:
        msg = f"world file {p}: invalid TOML: {err}"
        raise ConfigError(msg) from err
    return world_from_mapping(data, default_name=p.stem)


def _pair(value: Any, key: str) -> tuple[float, float]:
    try:
        n, e = (float(v) for v in value)
    except (TypeError, ValueError) as err:
        msg = f"world: {key} must be [north_m, east_m], got {value!r}"
        raise ConfigError(msg) from err
    if not (math.isfinite(n) and math.isfinite(e)):
        msg = f"world: {key} must be finite, got {value!r}"
        raise ConfigError(msg)
    return n, e


def _num(table: Mapping[str, Any], key: str, where: str, default: float, *, minimum: float = 0.0) -> float:
    value = table.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float):
        msg = f"world: {where}.{key} must be a number, got {value!r}"
        raise ConfigError(msg)
    if not value >= minimum:
        msg = f"world: {where}.{key} must be >= {minimum}, got {value!r}"
        raise ConfigError(msg)
    return float(value)


def _check_keys(table: Any, kind: str, index: int) -> Mapping[str, Any]:
    if not isinstance(table, Mapping):
        msg = f"world: {kind}[{index}] must be a table"
        raise ConfigError(msg)
    unknown = set(table) - _KEYS[kind]
    if unknown:
        msg = f"world: {kind}[{index}] has unknown keys {sorted(unknown)}; allowed: {sorted(_KEYS[kind])}"
        raise ConfigError(msg)
    return table


def _cylinders(data: Mapping[str, Any]) -> tuple[list[tuple[float, float]], list[float], list[float]]:
    """The ``[[cylinder]]`` tables: centres (north, east) m, radii m, heights m."""
    centres: list[tuple[float, float]] = []
    radii: list[float] = []
    heights: list[float] = []
    for i, raw in enumerate(data.get("cylinder", [])):
        t = _check_keys(raw, "cylinder", i)
        if "ne_m" not in t:
            msg = f"world: cylinder[{i}] needs ne_m = [north_m, east_m]"
            raise ConfigError(msg)
        centres.append(_pair(t["ne_m"], f"cylinder[{i}].ne_m"))
        radii.append(_num(t, "radius_m", f"cylinder[{i}]", 0.0))
        heights.append(_num(t, "height_m", f"cylinder[{i}]", math.inf, minimum=1e-9))
    return centres, radii, heights


def _walls(data: Mapping[str, Any]) -> tuple[list[np.ndarray], list[float], list[float]]:
    """The ``[[wall]]`` then ``[[polygon]]`` tables: segments (N, 2, 2) NE m, thicknesses m, heights m."""
    segs: list[np.ndarray] = []
    thick: list[float] = []
    wall_h: list[float] = []
    for i, raw in enumerate(data.get("wall", [])):
        t = _check_keys(raw, "wall", i)
        if "from_ne_m" not in t or "to_ne_m" not in t:
            msg = f"world: wall[{i}] needs from_ne_m and to_ne_m"
            raise ConfigError(msg)
        segs.append(
            np.array([[_pair(t["from_ne_m"], f"wall[{i}].from_ne_m"), _pair(t["to_ne_m"], f"wall[{i}].to_ne_m")]])
        )
        thick.append(_num(t, "thickness_m", f"wall[{i}]", 0.0))
        wall_h.append(_num(t, "height_m", f"wall[{i}]", math.inf, minimum=1e-9))
    for i, raw in enumerate(data.get("polygon", [])):
        t = _check_keys(raw, "polygon", i)
        closed = t.get("closed", True)
        if not isinstance(closed, bool):
            msg = f"world: polygon[{i}].closed must be true or false"
            raise ConfigError(msg)
        pts = [_pair(p, f"polygon[{i}].points_ne_m") for p in t.get("points_ne_m", [])]
        poly = World.polygon_segments(pts, closed=closed)
        segs.append(poly)
        thick.extend([_num(t, "thickness_m", f"polygon[{i}]", 0.0)] * len(poly))
        wall_h.extend([_num(t, "height_m", f"polygon[{i}]", math.inf, minimum=1e-9)] * len(poly))
    return segs, thick, wall_h


def _with_random_field(world: World, raw: Any, name: str) -> World:
    """``world`` merged with the ``[random_field]`` table's seeded paper field."""
    t = _check_keys(raw, "random_field", 0)
    obstacles = t.get("obstacles", "low")
    seed = t.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        msg = f"world: random_field.seed must be an integer >= 0, got {seed!r}"
        raise ConfigError(msg)
    field = paper_field(
        str(t.get("preset", "reference")),
        obstacles if isinstance(obstacles, str) else int(obstacles),
        np.random.default_rng(seed),
        radius_m=_num(t, "radius_m", "random_field", 0.0),
    )
    return world.merged(field, name=name)


def world_from_mapping(data: Mapping[str, Any], *, default_name: str = "world") -> World:
    """Build a World from a parsed TOML/JSON mapping in the documented format."""
    unknown = set(data) - _TOP_KEYS
    if unknown:
        msg = f"world: unknown top-level keys {sorted(unknown)}; allowed: {sorted(_TOP_KEYS)}"
        raise ConfigError(msg)
    centres, radii, heights = _cylinders(data)
    segs, thick, wall_h = _walls(data)
    name = data.get("name", default_name)
    start = _pair(data["start_ne_m"], "start_ne_m") if "start_ne_m" in data else None
    goal = _pair(data["goal_ne_m"], "goal_ne_m") if "goal_ne_m" in data else None
    world = World.from_obstacles(
        np.array(centres, dtype=np.float64).reshape(-1, 2),
        np.array(radii, dtype=np.float64),
        heights_m=np.array(heights, dtype=np.float64),
        walls_ne_m=np.concatenate(segs) if segs else np.zeros((0, 2, 2)),
        wall_thickness_m=np.array(thick, dtype=np.float64),
        wall_heights_m=np.array(wall_h, dtype=np.float64),
        name=str(name),
        start_ne_m=start,
        goal_ne_m=goal,
    )
    if "area_ne_m" in data:
        world = dataclasses.replace(world, area_ne_m=_area(data["area_ne_m"]))
    if "keepout" in data:
        zones = [_check_keys(raw, "keepout", i).get("points_ne_m", []) for i, raw in enumerate(data["keepout"])]
        keepouts = tuple(tuple(_pair(p, f"keepout[{i}].points_ne_m") for p in z) for i, z in enumerate(zones))
        world = dataclasses.replace(world, keepouts_ne_m=keepouts)
    if "random_field" in data:
        world = _with_random_field(world, data["random_field"], str(name))
    return world


def _area(value: Any) -> FlyingArea:
    """``area_ne_m = [[north_min, east_min], [north_max, east_max]]`` (a rectangle's corners) or ``[[north, east],
    ...]`` with three or more pairs (a polygon's vertices, ``World`` checks it)."""
    if isinstance(value, str) or not isinstance(value, list | tuple) or len(value) < 2:
        msg = (
            "world: area_ne_m must be [[north_min, east_min], [north_max, east_max]] or [[north, east], ...], "
            f"got {value!r}"
        )
        raise ConfigError(msg)
    pairs = [_pair(v, f"area_ne_m[{i}]") for i, v in enumerate(value)]
    if len(pairs) > 2:
        return tuple(pairs)
    return (*pairs[0], *pairs[1])
