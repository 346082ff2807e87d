"""sim.world: obstacle worlds for the simulator (cylinders, walls, polygons), the paper's random field, world files.

World coordinates are local NED north/east metres relative to the vehicle's EKF origin (= home).
"""

from __future__ import annotations

from sim.world.field import (
    DENSITIES,
    FIELD_PRESETS,
    MAX_OBSTACLES,
    PAPER_START_NE_M,
    PAPER_TARGET_NE_M,
    FieldPreset,
    paper_field,
    parse_field_spec,
)
from sim.world.files import EXAMPLES_DIR, bundled_world_names, example_world_path, load_world, world_from_mapping
from sim.world.model import World

__all__ = [
    "DENSITIES",
    "EXAMPLES_DIR",
    "FIELD_PRESETS",
    "MAX_OBSTACLES",
    "PAPER_START_NE_M",
    "PAPER_TARGET_NE_M",
    "FieldPreset",
    "World",
    "bundled_world_names",
    "example_world_path",
    "load_world",
    "paper_field",
    "parse_field_spec",
    "world_from_mapping",
]
