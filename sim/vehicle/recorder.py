"""What a flight leaves behind: the trajectory (at ``trajectory_rate_hz``), the path length, the lowest clearance."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from sim.world.model import FloatArray

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["FlightRecorder", "flight_result"]


class FlightRecorder:
    """Appends to the trajectory at a fixed simulated rate (or when forced: start, crash)."""

    def __init__(self, trajectory_rate_hz: float) -> None:
        self.period_s = 1.0 / trajectory_rate_hz
        self.next_t_s = 0.0
        self.trajectory_t_s: list[float] = []
        self.trajectory_ned_m: list[list[float]] = []
        self.path_length_m = 0.0
        self.min_clearance_m = math.inf

    def record(self, t_s: float, pos_ned_m: FloatArray, *, force: bool = False) -> None:
        if force or t_s >= self.next_t_s - 1e-9:
            self.trajectory_t_s.append(round(t_s, 6))
            self.trajectory_ned_m.append([round(float(x), 4) for x in pos_ned_m])
            self.next_t_s = t_s + self.period_s

    def moved(self, prev_ned_m: FloatArray, pos_ned_m: FloatArray) -> None:
        d = pos_ned_m - prev_ned_m
        self.path_length_m += math.sqrt(float(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))

    def clearance(self, clearance_m: float) -> None:
        self.min_clearance_m = min(self.min_clearance_m, clearance_m)


def flight_result(v: VehicleEngine) -> dict[str, Any]:
    """The engine's flight result (JSON-ready); the format is documented in docs/simulator.md."""
    return {
        "schema": "apf.sim_result/1",
        "profile": v.profile.value,
        "dynamics": v.cfg.dynamics.value,
        "seed": v.cfg.seed,
        "collided": v.crash_info is not None and v.crash_info["obstacle_id"] >= 0,
        "crashed": v.crashed,
        "crashed_at": v.crash_info,
        "sim_time_s": round(v.t_s, 6),
        "path_length_m": v.path_length_m,
        "min_clearance_m": v.min_clearance_m if math.isfinite(v.min_clearance_m) else None,
        "fence_breaches": v.fence.guard.breaches,  # breaches the autopilot acted on (sim.vehicle.fencebreach)
        "vehicle_radius_m": v.params["SIM_VEH_RADIUS"],
        "final_pos_ned_m": v.state.pos_ned_m.tolist(),
        "final_mode": v.mode_name(),
        "armed": v.armed,
        "on_ground": v.state.on_ground,
        "trajectory_t_s": list(v.trajectory_t_s),
        "trajectory_ned_m": [list(p) for p in v.trajectory_ned_m],
        "statustexts": [[s.t_s, s.severity, s.text] for s in v.statustexts],
        "params": dict(v.params.items()),
        "world": v.world.describe(),
    }
