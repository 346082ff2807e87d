"""The range sensor on the simulated vehicle: scans the world at SIM_RNG_RATE and sends the configured messages."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sim.vehicle.sensor import distance_sensor_msgs, obstacle_distance_3d_msgs, obstacle_distance_msg, scan_world

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["RangeSensorDriver"]


class RangeSensorDriver:
    """Owns the scan schedule; each scan goes out on the sensor's links and to the engine's scan listeners."""

    def __init__(self) -> None:
        self.next_scan_t = 0.0

    def tick(self, v: VehicleEngine) -> None:
        rate = v.params["SIM_RNG_RATE"]
        if rate <= 0 or v.t_s < self.next_scan_t - 1e-9:
            return
        self.next_scan_t = max(self.next_scan_t + 1.0 / rate, v.t_s)
        sensor = v.cfg.sensor
        scan = scan_world(
            v.world,
            sensor,
            t_s=v.boot_s,
            pos_ned_m=v.state.pos_ned_m,
            yaw_rad=v.state.yaw_rad,
            min_range_m=v.params["SIM_RNG_MIN"],
            max_range_m=v.params["SIM_RNG_MAX"],
            noise_sd_m=v.params["SIM_RNG_NOISE"],
            dropout_prob=v.params["SIM_RNG_DROP"],
            rng=v.rng_sensor,
            octants="distance_sensor" in sensor.messages,
            points="obstacle_distance_3d" in sensor.messages,
        )
        v.last_scan = scan
        msgs: list[Any] = []
        if "obstacle_distance" in sensor.messages:
            msgs.append(obstacle_distance_msg(v.mav, scan, sensor))
        if "distance_sensor" in sensor.messages:
            msgs.extend(distance_sensor_msgs(v.mav, scan))
        if "obstacle_distance_3d" in sensor.messages:
            msgs.extend(obstacle_distance_3d_msgs(v.mav, scan))
        for m in msgs:
            if sensor.links is None:
                v.emit(None, m)
            else:
                for i in sensor.links:
                    if 0 <= i < v.n_links:
                        v.emit(i, m)
        for fn in v.scan_listeners:
            fn(scan)
