"""What a flight leaves behind: the trajectory (at ``trajectory_rate_hz``), the path length, the lowest clearance."""

from __future__ import annotations

import math

from sim.world.model import FloatArray

__all__ = ["FlightRecorder"]


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
