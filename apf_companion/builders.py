"""The service's parts built from a ``ServiceConfig``: each reads the config here, once, and keeps its own params."""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable
from typing import Any

import numpy as np

from apf_companion.config import ServiceConfig
from apf_companion.errors import ConfigError
from apf_companion.goal import Route, load_route
from apf_companion.handlers import HandlerParams
from apf_companion.links import MavlinkLink
from apf_companion.links.messages import Source
from apf_companion.navigator import Navigator, NavigatorParams, ObstacleView
from apf_companion.outbox import Outbox
from apf_companion.perception import PerceptionParams, PoseLimits
from apf_companion.planning import PlannerName, PlannerParams, get_planner
from apf_companion.reporter import ReporterParams
from apf_companion.takeover import TakeoverParams

__all__ = [
    "build_navigator",
    "build_outbox",
    "build_planner",
    "handler_params",
    "initial_route",
    "navigator_params",
    "perception_params",
    "reporter_params",
    "takeover_params",
]


def build_planner(config: ServiceConfig) -> Any:
    """The configured planner: preset, then ``[planner.params]`` overrides, then ``dim``.

    Raises:
        ConfigError: unknown planner parameter or a value the planner refuses.
    """
    pc = config.planner
    params = PlannerParams.from_preset(pc.preset)
    current = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    overrides: dict[str, Any] = {}
    for key, raw in pc.params.items():
        value: Any = raw
        if key not in current or key == "dim":
            allowed = ", ".join(sorted(k for k in current if k != "dim"))
            msg = f"unknown planner parameter planner.params.{key} (allowed: {allowed}; dim is planner.dim)"
            raise ConfigError(msg)
        old = current[key]
        if isinstance(old, enum.Enum):
            try:
                value = type(old)(value)
            except ValueError as err:
                allowed = ", ".join(repr(m.value) for m in type(old))
                msg = f"planner.params.{key} must be one of {allowed}, got {value!r}"
                raise ConfigError(msg) from err
        elif isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        overrides[key] = value
    try:
        params = dataclasses.replace(params, **overrides, dim=pc.dim)
    except ConfigError as err:
        msg = f"planner.params: {err}"
        raise ConfigError(msg) from err
    return get_planner(pc.name, params)


#: Planners whose bacteria points keep rho_l from every known obstacle (Eq. (13)'s +inf inside rho_l).
_GUARDED_PLANNERS = frozenset({PlannerName.CR_BAPF, PlannerName.CR_BAPF_STAR})


def navigator_params(config: ServiceConfig, planner: Any) -> NavigatorParams:
    """The navigator's view of the config and of ``planner`` (``build_planner``): its step, and the clearance to
    keep: a planner's own swept clearance where it has one (bapf-nav: radius + margin + noise margin), else rho_l.
    The clearance drives the slow-down near obstacles for every planner and, for planners that promise it
    (bapf-nav, CR-BAPF, CR-BAPF*), the re-check of a planned point against obstacles remembered since."""
    own = getattr(planner, "clearance_m", None)
    clearance_m = float(own) if own is not None else float(planner.params.rho_l_m)
    guarded = own is not None or config.planner.name in _GUARDED_PLANNERS
    return NavigatorParams(
        dim=config.planner.dim,
        heartbeat_timeout_s=config.link.heartbeat_timeout_s,
        pose_max_age_s=config.cycle.pose_max_age_s,
        ranges_max_age_s=config.cycle.ranges_max_age_s,
        require_ranges=config.sensors.require_ranges,
        arrival_radius_m=config.cycle.arrival_radius_m,
        replan_radius_m=config.cycle.replan_radius_m,
        cruise_speed_m_s=config.cycle.cruise_speed_m_s,
        max_range_m=config.sensors.max_range_m,
        random_walk_budget=config.planner.random_walk_budget,
        progress_timeout_s=config.planner.progress_timeout_s,
        dry_run=config.dry_run,
        step_m=float(planner.params.step_m),
        target_guard_m=clearance_m if guarded else 0.0,
        clearance_m=clearance_m,
        reset_hold_s=config.safety.reset_hold_s,
        silent_horizon_s=config.safety.guid_timeout_s,
        silent_drift_m=config.safety.silent_drift_m,
        resume_after_link_lost=config.safety.resume_after_link_lost,
    )


def build_navigator(config: ServiceConfig, planner: Any, obstacles: ObstacleView) -> Navigator:
    """The decision core for ``planner`` (``build_planner``), reading ``obstacles`` (the perception front end)."""
    return Navigator(
        params=navigator_params(config, planner),
        planner=planner,
        obstacles=obstacles,
        rng=np.random.default_rng(config.planner.seed),
    )


def build_outbox(config: ServiceConfig, link: MavlinkLink | None, now_s: Callable[[], float]) -> Outbox:
    """The sending side towards the configured autopilot (silent in a dry run or without a link)."""
    lc = config.link
    return Outbox(
        link,
        dry_run=config.dry_run,
        target_system=lc.autopilot_sysid,
        target_component=lc.autopilot_compid,
        now_s=now_s,
    )


def perception_params(config: ServiceConfig) -> PerceptionParams:
    s, z = config.sensors, config.safety
    return PerceptionParams(
        max_range_m=s.max_range_m,
        memory_expiry_s=s.memory_expiry_s,
        merge_radius_m=s.merge_radius_m,
        max_points=s.max_points,
        surface_fill=s.surface_fill,
        surface_fill_spacing_m=s.surface_fill_spacing_m,
        surface_fill_max_gap_m=s.surface_fill_max_gap_m,
        surface_fill_line_tol_m=s.surface_fill_line_tol_m,
        pose_limits=PoseLimits(
            max_speed_m_s=z.max_speed_m_s,
            max_accel_m_s2=z.max_accel_m_s2,
            noise_m=z.pose_noise_m,
            max_abs_position_m=z.max_abs_position_m,
            time_jump_s=z.pose_time_jump_s,
            reset_samples=z.pose_reset_samples,
        ),
        clear_scans=z.clear_scans,
        clear_span_s=z.clear_span_s,
        sectors=z.sectors if s.require_ranges else 0,
        sector_max_age_s=z.sector_max_age_s,
    )


def takeover_params(config: ServiceConfig) -> TakeoverParams:
    a = config.autopilot
    return TakeoverParams(
        enabled=a.takeover and not config.dry_run,
        profile=a.profile,
        arm=a.arm,
        takeoff_alt_m=a.takeoff_alt_m,
        mode_timeout_s=a.mode_timeout_s,
        offboard_prestream_s=a.offboard_prestream_s,
    )


def handler_params(config: ServiceConfig) -> HandlerParams:
    lc = config.link
    return HandlerParams(
        autopilot=Source(lc.autopilot_sysid, lc.autopilot_compid),
        component_id=lc.component_id,
        gcs_sysids=lc.gcs_sysids,
        profile=config.autopilot.profile,
        dry_run=config.dry_run,
        mavlink_ranges=config.sensors.mavlink,
        telemetry_rate_hz=lc.telemetry_rate_hz,
        fly_config_goal_after_restart=config.goal.fly_after_restart,
    )


def reporter_params(config: ServiceConfig) -> ReporterParams:
    return ReporterParams(
        statustext=config.status.statustext,
        named_value_rate_hz=config.status.named_value_rate_hz,
        zenoh_status_key=config.zenoh.status_key,
        zenoh_status_rate_hz=config.zenoh.status_rate_hz,
        dry_run=config.dry_run,
    )


def initial_route(config: ServiceConfig) -> Route | None:
    """The goal from the config's ``[goal]`` (a point or a route file), if any."""
    g = config.goal
    if g.route:
        return load_route(config.resolve(g.route), source="config:route")
    if g.north_m is not None and g.east_m is not None:
        return Route.point(g.north_m, g.east_m, g.down_m, source="config")
    return None
