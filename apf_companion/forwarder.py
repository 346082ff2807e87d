"""OBSTACLE_DISTANCE forwarding: the companion's obstacle memory, told to the autopilot at a fixed rate.

Optional (``[sensors] forward_obstacle_distance``). Each period it reads the remembered points, the latest pose's
position and the heading now (``PerceptionFrontEnd.yaw_now``: the ATTITUDE samples carried to the present; the
autopilot keeps the sectors in the body frame, so they are computed with the heading they arrive at), encodes the
72 body-FRD sectors (``perception.obstacle_sectors_cm``) and sends them from our component id
(``Outbox.obstacle_distance``). ArduPilot's proximity library takes them with PRX1_TYPE = 2
(``AP_Proximity_MAV.cpp``); its backend reports "no data" 0.5 s after the last one, so the rate must stay well
above 2 Hz.

Without a fresh pose or a heading (no ATTITUDE for ``MAX_HEADING_AGE_S``) nothing is sent (counted in
``forward_skipped``): sectors placed with an old position would tell the autopilot about obstacles where they no
longer are; silence makes it mark proximity unhealthy instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from apf_companion.navigator import Navigator
from apf_companion.outbox import Outbox
from apf_companion.perception import PerceptionFrontEnd, obstacle_sectors_cm
from apf_companion.reporter import ServiceCounters

__all__ = ["ForwarderParams", "ObstacleForwarder"]

HEIGHT_WINDOW_M = 1.0  # remembered points this far above or below the vehicle are in its horizontal scan


@dataclass(frozen=True, slots=True, kw_only=True)
class ForwarderParams:
    """What the forwarder needs of the configuration (``[sensors]`` forward_* and max_range_m)."""

    enabled: bool = False
    rate_hz: float = 10.0
    max_range_m: float = 8.0
    height_window_m: float = HEIGHT_WINDOW_M


class ObstacleForwarder:
    """Sends the obstacle view as OBSTACLE_DISTANCE every ``1 / rate_hz`` (service clock)."""

    def __init__(
        self,
        params: ForwarderParams,
        *,
        perception: PerceptionFrontEnd,
        navigator: Navigator,
        outbox: Outbox,
        counters: ServiceCounters,
    ) -> None:
        self.params = params
        self.perception = perception
        self.navigator = navigator
        self.outbox = outbox
        self.counters = counters
        self.period_s = 1.0 / params.rate_hz
        self._next_s = -math.inf

    def due(self, now_s: float) -> float:
        """Send if due; the service time of the next send."""
        if now_s >= self._next_s:
            self._next_s = max(self._next_s + self.period_s, now_s)
            self.send(now_s)
        return self._next_s

    def send(self, now_s: float) -> bool:
        """One OBSTACLE_DISTANCE from the view at ``now_s``; False (counted) without a fresh pose or heading."""
        pose, yaw = self.navigator.pose, self.perception.yaw_now(now_s)
        boot_s = self.perception.autopilot_boot_s(now_s)
        if pose is None or yaw is None or boot_s is None or not self.navigator.pose_fresh(now_s):
            self.counters.forward_skipped += 1
            return False
        sectors = obstacle_sectors_cm(
            self.perception.points(now_s),
            pose.pos_ned_m,
            yaw,
            max_range_m=self.params.max_range_m,
            height_window_m=self.params.height_window_m,
            measured=lambda bearing: self.perception.direction_fresh(bearing, now_s),
        )
        time_usec = max(0, round(boot_s * 1e6))  # the autopilot's clock, as its own messages are stamped
        return self.outbox.obstacle_distance(
            time_usec, sectors.distances_cm, sectors.min_distance_cm, sectors.max_distance_cm
        )
