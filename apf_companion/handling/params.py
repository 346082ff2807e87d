"""What the autopilot handlers and their parts read of the configuration."""

from __future__ import annotations

from dataclasses import dataclass, field

from apf_companion.adopt import AdoptParams
from apf_companion.autopilot import Autopilot
from apf_companion.links.messages import Source

__all__ = ["BROADCAST", "HandlerParams"]

BROADCAST = 0  # target_system / target_component 0: every system / every component (MAVLink routing)


@dataclass(frozen=True, slots=True, kw_only=True)
class HandlerParams:
    autopilot: Source
    component_id: int = 191  # ours
    gcs_sysids: tuple[int, ...] = (255,)
    profile: Autopilot = Autopilot.ARDUPILOT
    dry_run: bool = False
    mavlink_ranges: bool = True  # [sensors] mavlink
    telemetry_rate_hz: float = 20.0
    sensor_sources: tuple[Source, ...] = ()  # [sensors] mavlink_sources
    forwarding: bool = False  # [sensors] forward_obstacle_distance
    adopt: AdoptParams = field(default_factory=AdoptParams)
    fly_config_goal_after_restart: bool = False  # [goal] fly_after_restart
