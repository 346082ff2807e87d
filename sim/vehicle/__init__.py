"""sim.vehicle: a pure-Python MAVLink vehicle simulator that behaves like ArduCopter and PX4.

In-process API::

    from sim.vehicle import Simulator, SimConfig, SpawnConfig
    async with await Simulator.start(SimConfig(links=["udpout:127.0.0.1:14550"], profile="px4")) as sim:
        ...  # sim.vehicle (position, mode, armed, crashed), sim.result()

The pure engine (``VehicleEngine``) runs the same rules without sockets on a simulated clock; docs/simulator.md
maps its modules (profiles, message handlers, telemetry, dynamics).
"""

from __future__ import annotations

from sim.vehicle.config import (
    DEFAULT_RATES_HZ,
    Dynamics,
    EngineConfig,
    HomeConfig,
    SpawnConfig,
    StatusText,
    VehicleSnapshot,
)
from sim.vehicle.dynamics import ControlTarget, Limits, TargetKind, VehicleState
from sim.vehicle.engine import VehicleEngine
from sim.vehicle.params import ParamSpec, ParamTable, param_specs
from sim.vehicle.sensor import SENSOR_MESSAGES, RangeSensorConfig, Scan, scan_world
from sim.vehicle.simulator import SimConfig, Simulator, ZenohOutput, scan_to_range_scan, write_result_json

__all__ = [
    "DEFAULT_RATES_HZ",
    "SENSOR_MESSAGES",
    "ControlTarget",
    "Dynamics",
    "EngineConfig",
    "HomeConfig",
    "Limits",
    "ParamSpec",
    "ParamTable",
    "RangeSensorConfig",
    "Scan",
    "SimConfig",
    "Simulator",
    "SpawnConfig",
    "StatusText",
    "TargetKind",
    "VehicleEngine",
    "VehicleSnapshot",
    "VehicleState",
    "ZenohOutput",
    "param_specs",
    "scan_to_range_scan",
    "scan_world",
    "write_result_json",
]
