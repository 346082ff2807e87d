"""The service's parts built from a ``ServiceConfig``: each reads the config here, once, and keeps its own params."""

from __future__ import annotations

import dataclasses
import enum
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from apf_companion.adopt import AdoptParams
from apf_companion.autopilot import Autopilot, guided_mode_name
from apf_companion.config import ServiceConfig, did_you_mean
from apf_companion.errors import ConfigError
from apf_companion.fence import FenceArea
from apf_companion.forwarder import ForwarderParams
from apf_companion.goal import Route, load_route, route_outside_limits
from apf_companion.goaladmission import AdmissionParams
from apf_companion.handlers import COMMAND_MESSAGES, HandlerParams
from apf_companion.linkquality import CautionParams
from apf_companion.links import (
    MavlinkLink,
    SigningParams,
    TimestampFile,
    accept_unsigned_telemetry,
    load_signing_key,
    start_timestamp,
)
from apf_companion.links.messages import Source
from apf_companion.navigator import Navigator, NavigatorParams, ObstacleView
from apf_companion.outbox import Outbox
from apf_companion.perception import PerceptionParams, PoseLimits, ScanFrame
from apf_companion.planning import BapfNavPlanner, FlyingArea, KeepOuts, PlannerName, PlannerParams, get_planner
from apf_companion.reporter import ReporterParams
from apf_companion.takeover import TakeoverParams

__all__ = [
    "SigningSetup",
    "admission_params",
    "build_navigator",
    "build_outbox",
    "build_planner",
    "config_with_fence",
    "flying_area",
    "forwarder_params",
    "handler_params",
    "has_zones",
    "initial_route",
    "keepout_zones",
    "navigator_params",
    "perception_params",
    "planner_params",
    "reporter_params",
    "signing_setup",
    "takeover_params",
]


def build_planner(config: ServiceConfig) -> Any:
    """The configured planner: ``planner_params``, then the planner built from them (bapf-nav builds its maps here:
    about 1.2 ms on the development VM).

    Raises:
        ConfigError: unknown planner parameters or values the planner refuses (all of them, one per line).
    """
    return get_planner(config.planner.name, planner_params(config))


def planner_params(config: ServiceConfig) -> PlannerParams:
    """The planner's parameters: preset, then ``[planner.params]`` overrides, then ``dim``; checked as the planner
    checks them (``PlannerParams``'s own checks: the planners' constructors check nothing more), without building
    the planner (a PARAM_SET is checked with this, ``apf_companion.params``).

    Raises:
        ConfigError: unknown planner parameters or values the planner refuses (all of them, one per line).
    """
    pc = config.planner
    params = PlannerParams.from_preset(pc.preset)
    current = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    overrides: dict[str, Any] = {}
    errors: list[str] = []
    for key, raw in pc.params.items():
        try:
            overrides[key] = _override(key, raw, current)
        except ConfigError as err:
            errors.append(str(err))
    try:
        checked = dataclasses.replace(params, **overrides, dim=pc.dim)
        if not errors:
            return checked
    except ConfigError as whole:
        for key, value in overrides.items():  # each override alone: every refused value, not only the first
            try:
                dataclasses.replace(params, **{key: value}, dim=pc.dim)
            except ConfigError as err:
                if f"PlannerParams.{key} " in str(err):  # about this key, not a rule it shares with a default
                    errors.append(f"planner.params: {err}")
        errors = errors or [f"planner.params: {whole}"]
    if len(errors) == 1:
        raise ConfigError(errors[0])
    lines = "\n".join(f"  - {e}" for e in errors)
    raise ConfigError(f"{len(errors)} config errors:\n{lines}")


def _override(key: str, value: Any, current: dict[str, Any]) -> Any:
    """One ``[planner.params]`` value as the PlannerParams field's type; ConfigError naming the key."""
    if key not in current or key == "dim":
        names = sorted(k for k in current if k != "dim")
        hint = did_you_mean(key, names)
        msg = f"unknown planner parameter planner.params.{key}{hint} (allowed: {', '.join(names)}; dim is planner.dim)"
        raise ConfigError(msg)
    old = current[key]
    if isinstance(old, enum.Enum):
        try:
            return type(old)(value)
        except ValueError as err:
            allowed = ", ".join(repr(m.value) for m in type(old))
            msg = f"planner.params.{key} must be one of {allowed}, got {value!r}"
            raise ConfigError(msg) from err
    if isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


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
    # Where the vehicle can be (apf_companion.envelope): never inside radius + margin, the clearance the user asked
    # for; the planner's noise margin on top is for its plan, not for the braking envelope.
    tracking_m = min(clearance_m, float(planner.params.vehicle_radius_m + planner.params.safety_margin_m))
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
        brake_accel_m_s2=config.safety.brake_accel_m_s2,
        brake_latency_s=config.safety.brake_latency_s,
        tracking_clearance_m=tracking_m,
        caution=CautionParams(
            min_scale=config.safety.caution_min_scale,
            full_loss=config.safety.caution_full_loss,
            ok_age_s=config.safety.caution_ok_age_s,
            full_age_s=config.cycle.pose_max_age_s,
            window_s=config.safety.caution_window_s,
        ),
        resume_after_link_lost=config.safety.resume_after_link_lost,
        takeover=config.autopilot.takeover,
        guided_mode=guided_mode_name(config.autopilot.profile),
        setpoints_end_failsafe=config.autopilot.profile is Autopilot.PX4,
        yaw_travel=config.autopilot.yaw_travel,
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
        obstacle_distance_frame=ScanFrame.BODY_FRD if s.obstacle_distance_frame == "body_frd" else None,
        obstacle_distance_mount_yaw_rad=math.radians(s.obstacle_distance_mount_yaw_deg),
        laserscan_mount_yaw_rad=math.radians(s.laserscan_mount_yaw_deg),
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
        ready_timeout_s=a.ready_timeout_s,
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
        sensor_sources=tuple(Source(system, component) for system, component in config.sensors.source_ids()),
        forwarding=config.sensors.forward_obstacle_distance,
        adopt=AdoptParams(enabled=config.goal.adopt_autopilot_target, tolerance_m=config.goal.adopt_tolerance_m),
        fly_config_goal_after_restart=config.goal.fly_after_restart,
    )


def admission_params(config: ServiceConfig) -> AdmissionParams:
    g = config.goal
    return AdmissionParams(
        max_altitude_m=g.max_altitude_m,
        min_altitude_m=g.min_altitude_m,
        max_distance_m=g.max_distance_m,
        exit_when_done=config.exit_when_done,
    )


def forwarder_params(config: ServiceConfig) -> ForwarderParams:
    s = config.sensors
    return ForwarderParams(enabled=s.forward_obstacle_distance, rate_hz=s.forward_rate_hz, max_range_m=s.max_range_m)


def reporter_params(config: ServiceConfig) -> ReporterParams:
    return ReporterParams(
        statustext=config.status.statustext,
        named_value_rate_hz=config.status.named_value_rate_hz,
        zenoh_status_key=config.zenoh.status_key,
        zenoh_status_rate_hz=config.zenoh.status_rate_hz,
        dry_run=config.dry_run,
    )


def initial_route(config: ServiceConfig, planner: object) -> Route | None:
    """The goal from the config's ``[goal]`` (a point or a route file), if any; ``planner``: the one
    ``build_planner(config)`` built (its flying area).

    Raises:
        ConfigError: the route file is invalid, or a waypoint lies outside bapf-nav's flying area
            (``planner.params.nav_area_ne_m``) or in a keep-out zone, where the planner would give up at once.
    """
    g = config.goal
    route = None
    if g.route:
        route = load_route(config.resolve(g.route), source="config:route")
    elif g.north_m is not None and g.east_m is not None:
        route = Route.point(g.north_m, g.east_m, g.down_m, source="config")
    if route is not None:
        # A configured waypoint outside the flying area is a config error, not a STUCK after take-off.
        area, keepouts = flying_area(planner), keepout_zones(planner)
        why = route_outside_limits(
            route, None, max_altitude_m=0.0, max_distance_m=0.0, area_ne_m=area, keepouts_ne_m=keepouts
        )
        if why is not None:
            raise ConfigError(f"goal: {why}: bapf-nav would give up at once")
    return route


def flying_area(planner: object) -> FlyingArea | None:
    """The flying area bapf-nav plans over (its validated ``params.nav_area_ne_m``), or None: no area, or another
    planner (they do not use one)."""
    return planner.params.nav_area_ne_m if isinstance(planner, BapfNavPlanner) else None


def config_with_fence(config: ServiceConfig, area: FenceArea) -> ServiceConfig:
    """``config`` with the fence's zones as bapf-nav's ``nav_area_ne_m`` and ``nav_keepout_ne_m`` (as a config
    file would give them: lists), for ``build_planner`` to check. They replace the zones of an earlier fence; a
    fence without zones (none, or not used) leaves neither."""
    params = {k: v for k, v in config.planner.params.items() if k not in ("nav_area_ne_m", "nav_keepout_ne_m")}
    if area.polygon_ne_m is not None:
        params["nav_area_ne_m"] = [list(v) for v in area.polygon_ne_m]
    if area.keepouts_ne_m:
        params["nav_keepout_ne_m"] = [[list(v) for v in zone] for zone in area.keepouts_ne_m]
    return dataclasses.replace(config, planner=dataclasses.replace(config.planner, params=params))


def keepout_zones(planner: object) -> KeepOuts:
    """bapf-nav's keep-out zones (``params.nav_keepout_ne_m``); none for the other planners."""
    return planner.params.nav_keepout_ne_m if isinstance(planner, BapfNavPlanner) else ()


def has_zones(planner: object) -> bool:
    """Whether the planner plans over a flying area or round keep-out zones (bapf-nav's)."""
    return flying_area(planner) is not None or bool(keepout_zones(planner))


def fence_not_read(config: ServiceConfig, planner: object) -> str | None:
    """Why the service does not read the autopilot's fence as the flying area (``planner.fence_area``), or None
    when it does (with a link that sends: ``service._fence_reader``)."""
    if not isinstance(planner, BapfNavPlanner):
        return f"only bapf-nav plans over the autopilot's fence; {config.planner.name} does not read it"
    if not config.planner.fence_area:
        return "planner.fence_area is false: the fence is not read"
    if has_zones(planner):
        return "planner.params gives nav_area_ne_m or nav_keepout_ne_m: the config's zones win, the fence is not read"
    if config.dry_run:
        return "a dry run sends nothing: the fence is not read"
    return None


#: PlannerParams fields that one planner alone reads, by name prefix: nav_* only bapf-nav's modules
#: (apf_companion/planning/bapfnav.py, nav*.py), br_* only bendyruler.py, capf_* only capf.py.
_OWN_PARAMS: tuple[tuple[str, PlannerName], ...] = (
    ("nav_", PlannerName.BAPF_NAV),
    ("br_", PlannerName.BENDYRULER),
    ("capf_", PlannerName.CAPF),
)


def settings_not_used(config: ServiceConfig, planner: object) -> dict[str, str]:
    """The settings ``check-config`` prints that this configuration does not use, each with why: the fence
    settings (``fence_not_read``) and other planners' own parameters (``planner.params.nav_*``, ...)."""
    out: dict[str, str] = {}
    why = fence_not_read(config, planner)
    if why is not None:
        if config.planner.fence_area:  # false is in effect: it is what keeps the fence unread
            out["planner.fence_area"] = why
        out["planner.fence_poll_s"] = why
    for prefix, owner in _OWN_PARAMS:
        if config.planner.name != owner:
            out[f"planner.params.{prefix}*"] = f"{owner}'s parameters; {config.planner.name} does not read them"
    return out


@dataclass(frozen=True, slots=True)
class SigningSetup:
    """MAVLink 2 signing on the autopilot link: the link's parameters and where its timestamp is kept."""

    params: SigningParams
    timestamps: TimestampFile


def signing_setup(config: ServiceConfig, unix_s: float | None = None) -> SigningSetup | None:
    """Signing from ``[link] signing_*`` (None when no key file is set): the key (file mode checked), the first
    timestamp (max(now, persisted + 1 min)) and the unsigned-message rule (commands / telemetry).

    Raises:
        ConfigError: the key file is missing, not private (mode 600), malformed or all zero; the timestamp file
            is unreadable or malformed.
    """
    lc = config.link
    if not lc.signing_key_file:
        return None
    key_path = config.resolve(lc.signing_key_file)
    key = load_signing_key(key_path)
    if lc.signing_timestamp_file:
        ts_path = config.resolve(lc.signing_timestamp_file)
    else:
        ts_path = key_path.with_name(key_path.name + ".timestamp")
    store = TimestampFile(ts_path)
    initial = start_timestamp(store.load(), time.time() if unix_s is None else unix_s)
    rule = accept_unsigned_telemetry(
        COMMAND_MESSAGES, commands_ok=not lc.require_signed_commands, telemetry_ok=not lc.require_signed_telemetry
    )
    return SigningSetup(SigningParams(key=key, initial_timestamp=initial, accept_unsigned=rule), store)
