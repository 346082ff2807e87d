"""The service configuration: one TOML file, validated at start.

Every section is a frozen dataclass whose defaults are the documented defaults (docs/configuration.md has the
reference table, generated from these classes; ``deploy/apf-companion.toml`` is a commented example). Loading is
strict: an unknown key, a wrong type or a value outside its range raises ``ConfigError`` naming the key
(``cycle.rate_hz``) and the allowed range; a likely typo gets a suggestion. Nothing here touches the network.

Times are in the vehicle's time base. ``cycle.time_scale`` (default 1) is for simulated vehicles that run faster
than real time: the service's clock runs ``time_scale`` times faster than the wall clock, so every period,
staleness limit and timeout below keeps its meaning in vehicle seconds.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from apf_companion.autopilot import Autopilot
from apf_companion.errors import ConfigError
from apf_companion.links.endpoint import parse_endpoint
from apf_companion.planning.params import Preset
from apf_companion.planning.registry import ALL_PLANNER_NAMES, DEFAULT_PLANNER

__all__ = [
    "HEARTBEAT_TIMEOUT_RANGE_S",
    "MAX_AGE_RANGE_S",
    "MAX_FLIGHT_RANGE_S",
    "OBSTACLE_DISTANCE_FRAMES",
    "PLANNER_PRESETS",
    "RATE_RANGE_HZ",
    "TAKEOFF_ALT_RANGE_M",
    "TIME_SCALE_RANGE",
    "YAW_CHOICES",
    "AutopilotConfig",
    "CycleConfig",
    "GoalConfig",
    "LinkConfig",
    "PlannerConfig",
    "SafetyConfig",
    "SensorsConfig",
    "ServiceConfig",
    "StatusConfig",
    "VisualisationConfig",
    "ZenohSection",
    "config_from_mapping",
    "did_you_mean",
    "load_config",
    "parse_source",
]

PLANNER_PRESETS: tuple[str, ...] = tuple(Preset)
_PLANNER_NAMES = ALL_PLANNER_NAMES

# The allowed [lo, hi] of settings a simulated flight derives from its own options (``apf-sim fly`` checks its
# flags against these before it starts anything, sim/fly.py).
HEARTBEAT_TIMEOUT_RANGE_S: tuple[float, float] = (0.5, 60.0)  # link.heartbeat_timeout_s
TAKEOFF_ALT_RANGE_M: tuple[float, float] = (0.0, 500.0)  # autopilot.takeoff_alt_m
MIN_ALTITUDE_RANGE_M: tuple[float, float] = (-10_000.0, 10_000.0)  # goal.min_altitude_m (above home)
RATE_RANGE_HZ: tuple[float, float] = (1.0, 50.0)  # cycle.rate_hz
MAX_AGE_RANGE_S: tuple[float, float] = (0.02, 10.0)  # cycle.pose_max_age_s and cycle.ranges_max_age_s
TIME_SCALE_RANGE: tuple[float, float] = (0.1, 100.0)  # cycle.time_scale
MAX_FLIGHT_RANGE_S: tuple[float, float] = (0.0, 86400.0)  # max_flight_s
MAX_LINK_LOST_RANGE_S: tuple[float, float] = (0.0, 86400.0)  # max_link_lost_s
OBSTACLE_DISTANCE_FRAMES: tuple[str, ...] = ("as_sent", "body_frd")  # sensors.obstacle_distance_frame


def _fail(key: str, allowed: str, value: object) -> ConfigError:
    return ConfigError(f"{key} must be {allowed}, got {value!r}")


def _check_range(key: str, value: float, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False) -> None:
    """Raise ConfigError naming ``key`` unless lo <= value <= hi (open ends as asked); NaN always fails."""
    ok = math.isfinite(value) or (math.isinf(hi) and value == math.inf and not hi_open)
    ok = ok and (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        left = "(" if lo_open else "["
        right = ")" if hi_open else "]"
        raise _fail(key, f"in {left}{lo}, {hi}{right}", value)


def _check_id(key: str, value: int, lo: int = 1, hi: int = 255) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise _fail(key, f"an integer in [{lo}, {hi}]", value)


def parse_source(key: str, text: str) -> tuple[int, int]:
    """A MAVLink source ``"SYSID/COMPID"`` (both in [1, 255]) as (system, component); ConfigError naming ``key``."""
    allowed = "'SYSID/COMPID' with both ids in [1, 255], e.g. '1/158'"
    sys_text, sep, comp_text = str(text).partition("/")
    if not sep or not sys_text.strip().isdigit() or not comp_text.strip().isdigit():
        raise _fail(key, allowed, text)
    ids = int(sys_text), int(comp_text)
    if not all(1 <= i <= 255 for i in ids):
        raise _fail(key, allowed, text)
    return ids


@dataclass(frozen=True, slots=True, kw_only=True)
class LinkConfig:
    """``[link]``: the MAVLink link to the autopilot and the companion's identity.

    Attributes:
        connect: Autopilot endpoint, pymavlink or MAVSDK style (``udpin:127.0.0.1:14540``, ``tcp:host:5760``,
            ``/dev/serial0:921600``).
        autopilot_sysid: System id of the autopilot; our heartbeat uses it too (the vehicle's sysid).
        autopilot_compid: Component id of the autopilot (1).
        component_id: Our component id: 191 (MAV_COMP_ID_ONBOARD_COMPUTER) or e.g. 196 (OBSTACLE_AVOIDANCE).
            Never a ground station's id (190, or anything on a GCS sysid), nor ``autopilot_compid``: we send with
            the autopilot's system id, so the same component id would make our HEARTBEATs and setpoints its own.
        gcs_sysids: Systems allowed to send us commands (COMMAND_INT DO_REPOSITION addressed to us).
        heartbeat_timeout_s: No autopilot HEARTBEAT for this long -> LINK_LOST [s].
        telemetry_rate_hz: Rate requested for LOCAL_POSITION_NED and ATTITUDE (SET_MESSAGE_INTERVAL) [Hz].
        tlog: Path of the .tlog recording every frame in and out; "" = none.
        signing_key_file: MAVLink 2 signing key (32 raw bytes or 64 hex digits; mode 600, else the service refuses
            to start): every frame sent is signed and every frame received checked; "" = signing off.
        signing_timestamp_file: Where the signing timestamp is kept across restarts (saved every 30 s and at
            exit); "" = the key file's path plus ``.timestamp``.
        require_signed_commands: With a key: act on commands (COMMAND_INT / COMMAND_LONG such as DO_REPOSITION,
            SET_POSITION_TARGET_*, SET_MODE, PARAM_SET) only when signed with it; unsigned, wrongly signed or
            replayed ones are dropped and counted. Parameter reads follow ``require_signed_telemetry``.
        require_signed_telemetry: With a key: drop every other message that is not signed with it too (turn on
            when the autopilot signs: ArduPilot does on every channel once it has a key).
    """

    connect: str = "udpin:127.0.0.1:14540"
    autopilot_sysid: int = 1
    autopilot_compid: int = 1
    component_id: int = 191
    gcs_sysids: tuple[int, ...] = (255,)
    heartbeat_timeout_s: float = 3.0
    telemetry_rate_hz: float = 20.0
    tlog: str = ""
    signing_key_file: str = ""
    signing_timestamp_file: str = ""
    require_signed_commands: bool = True
    require_signed_telemetry: bool = False

    def __post_init__(self) -> None:
        if not self.signing_key_file:
            if self.require_signed_telemetry:
                raise _fail("link.require_signed_telemetry", "false unless link.signing_key_file is set", True)
            if self.signing_timestamp_file:
                raise _fail(
                    "link.signing_timestamp_file",
                    "empty unless link.signing_key_file is set",
                    self.signing_timestamp_file,
                )
        if not self.connect.strip():
            raise _fail("link.connect", "an endpoint such as 'udpin:127.0.0.1:14540'", self.connect)
        try:  # the parse ``run`` uses to open the link, so check-config refuses what run would
            parse_endpoint(self.connect)
        except ConfigError as err:
            raise ConfigError(f"link.connect: {err}") from err
        _check_id("link.autopilot_sysid", self.autopilot_sysid)
        _check_id("link.autopilot_compid", self.autopilot_compid)
        _check_id("link.component_id", self.component_id)
        if self.component_id == 190:
            raise _fail("link.component_id", "a companion id (191-194, 195, 196 ...), not 190 (GCS)", 190)
        if self.component_id == self.autopilot_compid:
            # We send as autopilot_sysid/component_id: the same pair would be the autopilot's HEARTBEAT and setpoints
            raise _fail(
                "link.component_id",
                "different from link.autopilot_compid (we send with the autopilot's system id)",
                self.component_id,
            )
        for sysid in self.gcs_sysids:
            _check_id("link.gcs_sysids[]", sysid)
            if sysid == self.autopilot_sysid:
                raise _fail("link.gcs_sysids[]", "different from link.autopilot_sysid", sysid)
        _check_range("link.heartbeat_timeout_s", self.heartbeat_timeout_s, *HEARTBEAT_TIMEOUT_RANGE_S)
        _check_range("link.telemetry_rate_hz", self.telemetry_rate_hz, 1.0, 100.0)


YAW_CHOICES = ("auto", "travel", "none")
"""``[autopilot] yaw``'s values (AutopilotConfig)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class AutopilotConfig:
    """``[autopilot]``: which autopilot rules to follow and how far the service may take control.

    Attributes:
        profile: "ardupilot" (GUIDED) or "px4" (OFFBOARD).
        takeover: Switch the autopilot to GUIDED / OFFBOARD when a goal arrives. False: the pilot switches; until
            then the state is WAITING_FOR_PILOT ("switch to GUIDED to fly", one STATUSTEXT), the service streams a
            hold at the current position (PX4 accepts OFFBOARD only with a setpoint stream) and plans nothing.
        arm: Arm the vehicle (simulated flights only; off by default).
        takeoff_alt_m: With ``arm``: take off to this height above home before navigating [m]; 0 = no takeoff.
        mode_timeout_s: Give up a mode switch (or arming) not confirmed by HEARTBEAT.custom_mode within this, once
            3 HEARTBEATs said "not yet" (fewer, on a lossy link: up to twice this) [s].
        offboard_prestream_s: PX4: stream setpoints this long before asking for OFFBOARD (PX4 wants > 1 s) [s].
        ready_timeout_s: Before taking over (mode, arming) wait at most this long for a position (LOCAL_POSITION_NED
            fresh) and, where the autopilot reports it, an EKF with a horizontal position (EKF_STATUS_REPORT); the
            goal is dropped after that. ArduCopter SITL has no position for about 20 s after boot [s].
        yaw: The heading sent with the setpoints: "travel" (the range sensor faces the step being flown: the nose
            for a forward sensor, the tail for a rear one, learnt from the ranges; a step refused towards a sector
            without recent ranges turns the sensor there first), "none" (no yaw: the autopilot's own) or
            "auto" (the default: "travel" on PX4, which otherwise keeps its heading; "none" on ArduPilot, whose
            GUIDED faces the direction of travel by itself). See docs/service.md, "Heading".
    """

    profile: Autopilot = Autopilot.ARDUPILOT
    takeover: bool = True
    arm: bool = False
    takeoff_alt_m: float = 0.0
    mode_timeout_s: float = 5.0
    offboard_prestream_s: float = 1.3
    ready_timeout_s: float = 90.0
    yaw: str = "auto"

    def __post_init__(self) -> None:
        if not isinstance(self.profile, Autopilot):
            raise _fail("autopilot.profile", "one of 'ardupilot', 'px4'", self.profile)
        if self.yaw not in YAW_CHOICES:
            hint = did_you_mean(str(self.yaw), YAW_CHOICES)
            allowed = ", ".join(map(repr, YAW_CHOICES))
            raise ConfigError(f"autopilot.yaw must be one of {allowed}, got {self.yaw!r}{hint}")
        _check_range("autopilot.takeoff_alt_m", self.takeoff_alt_m, *TAKEOFF_ALT_RANGE_M)
        _check_range("autopilot.mode_timeout_s", self.mode_timeout_s, 0.5, 60.0)
        _check_range("autopilot.offboard_prestream_s", self.offboard_prestream_s, 1.0, 10.0, lo_open=True)
        _check_range("autopilot.ready_timeout_s", self.ready_timeout_s, 1.0, 3600.0)

    @property
    def yaw_travel(self) -> bool:
        """Whether the setpoints carry the heading of travel (``yaw``, "auto" resolved by ``profile``)."""
        return self.yaw == "travel" or (self.yaw == "auto" and self.profile is Autopilot.PX4)


@dataclass(frozen=True, slots=True, kw_only=True)
class PlannerConfig:
    """``[planner]`` (+ optional ``[planner.params]``): which planner and its parameters.

    Attributes:
        name: One of bapf-nav (the product planner, default), capf, bapf, a-bapf, cr-bapf, cr-bapf* (the
            paper's) or bendyruler (a comparison baseline).
        preset: Parameter preset: "default" (the paper's Table), "paper" or "reference" (docs/paper/notes.md).
        dim: 2 (plan north/east at the goal's altitude) or 3.
        seed: Seed of the random walk's generator (repeatable flights).
        random_walk_budget: Consecutive cycles without a greedy move (random walk or local minimum) after
            which the service gives up: STUCK.
        progress_timeout_s: No new best distance to the goal (by 0.1 m) for this long -> STUCK [s].
        fence_area: bapf-nav (the other planners never read the fence) with no flying area and no keep-out zone
            in params (nav_area_ne_m, nav_keepout_ne_m): read the autopilot's fence at start, and plan over its
            inclusion zones (their intersection, or union with ArduPilot's FENCE_OPTIONS) and round its exclusion
            zones once it is read, with its parameters: the edges kept FENCE_MARGIN away, its circle round home,
            ceiling and floor (docs/service.md, "The autopilot's fence" and "The autopilot's fence parameters").
        fence_poll_s: With ``fence_area``: read the fence again this long after each read, so a fence changed
            on the ground station in flight is planned over [s]; sooner when the autopilot's fence id changes
            (PX4); 0 = read once at start.
        params: Overrides of PlannerParams fields (e.g. step_m, rho_u_m; for bapf-nav vehicle_radius_m,
            safety_margin_m, noise_std_m, noise_k and the nav_* fields), validated by the planner. Values are
            numbers, strings, booleans, or lists of numbers or of such lists (bapf-nav's flying area,
            nav_area_ne_m: a rectangle or a polygon; its keep-out zones, nav_keepout_ne_m: a list of polygons).
    """

    name: str = str(DEFAULT_PLANNER)
    preset: str = "default"
    dim: int = 2
    seed: int = 0
    random_walk_budget: int = 100
    progress_timeout_s: float = 60.0
    fence_area: bool = True
    fence_poll_s: float = 5.0
    params: Mapping[str, float | int | bool | str | list[float] | list[list[float]] | list[list[list[float]]]] = field(
        default_factory=dict
    )

    def __post_init__(self) -> None:
        if self.name not in _PLANNER_NAMES:
            raise _fail("planner.name", f"one of {', '.join(_PLANNER_NAMES)}", self.name)
        if self.preset not in PLANNER_PRESETS:
            raise _fail("planner.preset", f"one of {', '.join(PLANNER_PRESETS)}", self.preset)
        if self.dim not in (2, 3):
            raise _fail("planner.dim", "2 or 3", self.dim)
        if not isinstance(self.seed, int) or self.seed < 0:
            raise _fail("planner.seed", "an integer >= 0", self.seed)
        if not isinstance(self.random_walk_budget, int) or not 1 <= self.random_walk_budget <= 100_000:
            raise _fail("planner.random_walk_budget", "an integer in [1, 100000]", self.random_walk_budget)
        _check_range("planner.progress_timeout_s", self.progress_timeout_s, 1.0, 3600.0)
        if self.fence_poll_s != 0.0:
            _check_range("planner.fence_poll_s", self.fence_poll_s, 1.0, 3600.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class CycleConfig:
    """``[cycle]``: the planning loop and its freshness limits.

    Attributes:
        rate_hz: Planner cycles per (vehicle) second; each fresh cycle sends one setpoint [Hz].
        pose_max_age_s: A pose older than this is stale -> HOLDING: one hold at the last known position, then
            silence; the first fresh pose after it fixes the hold anew where the vehicle is then [s].
        ranges_max_age_s: Ranges older than this are stale -> HOLDING [s].
        cruise_speed_m_s: Velocity feed-forward along the planned step [m/s].
        arrival_radius_m: Within this distance of the goal -> ARRIVED (the paper's 0.7 m) [m].
        replan_radius_m: The vehicle flies to each planned bacteria point and the next step is planned from
            that point once the vehicle is this close to it (the paper's path of bacteria points) [m].
        time_scale: Vehicle seconds per wall second (simulated vehicles with a speed-up; 1 on real hardware).
        realtime_priority: ``apf-companion run`` asks for SCHED_FIFO at this priority, 1-99, so a cycle does not
            wait behind other processes (apf_companion/realtime.py; refused without RLIMIT_RTPRIO: then the normal
            scheduler); 0 = never ask.
    """

    rate_hz: float = 10.0
    pose_max_age_s: float = 0.5
    ranges_max_age_s: float = 0.5
    cruise_speed_m_s: float = 1.0
    arrival_radius_m: float = 0.7
    replan_radius_m: float = 0.1
    time_scale: float = 1.0
    realtime_priority: int = 5

    def __post_init__(self) -> None:
        _check_range("cycle.rate_hz", self.rate_hz, *RATE_RANGE_HZ)
        _check_range("cycle.pose_max_age_s", self.pose_max_age_s, *MAX_AGE_RANGE_S)
        _check_range("cycle.ranges_max_age_s", self.ranges_max_age_s, *MAX_AGE_RANGE_S)
        _check_range("cycle.cruise_speed_m_s", self.cruise_speed_m_s, 0.0, 20.0, lo_open=True)
        _check_range("cycle.arrival_radius_m", self.arrival_radius_m, 0.0, 100.0, lo_open=True)
        _check_range("cycle.replan_radius_m", self.replan_radius_m, 0.0, 10.0, lo_open=True)
        _check_range("cycle.time_scale", self.time_scale, *TIME_SCALE_RANGE)
        _check_id("cycle.realtime_priority", self.realtime_priority, 0, 99)


@dataclass(frozen=True, slots=True, kw_only=True)
class GoalConfig:
    """``[goal]``: the goal at start (none = IDLE until one arrives over MAVLink or zenoh).

    Attributes:
        north_m, east_m, down_m: A single goal in local NED [m]; ``down_m`` omitted = keep the altitude.
        route: A route file instead (TOML ``[[waypoint]]`` tables or CSV lines ``north,east[,down]``),
            relative paths resolved against the config file.
        adopt_autopilot_target: Take the autopilot's new guided target (a ground station's "Fly here" / "Go to
            location" / MAVProxy ``guided``, seen in POSITION_TARGET_GLOBAL_INT / _LOCAL_NED) as the goal and fly
            there around obstacles (docs/ecosystem.md).
        adopt_tolerance_m: A reported target within this of a setpoint the service sent (or of its goal, or of
            the vehicle) is not a new goal [m].
        fly_after_restart: Fly this goal even when the service starts with the vehicle already flying (armed) in
            GUIDED / OFFBOARD, i.e. restarted mid-flight (systemd ``Restart=``, a watchdog kill). False (default):
            the goal in the file is not fresh then: the service holds position, says why, and waits for a goal
            sent now (DO_REPOSITION, zenoh). A ``--goal`` / ``--route`` on the command line is always flown.
        max_altitude_m: A goal (from any source) more than this above home is refused and counted in
            ``bad_goals`` [m]; 0 = no limit. 120 m: the usual limit for open-category flights.
        min_altitude_m: ... or one less than this above home (the EKF origin) [m]: 1 m keeps goals off and out of
            the ground. Negative lets goals lie that far below home (a valley below the take-off point); 0 = not
            below home; there is no "off". The autopilot's fence floor (FENCE_ALT_MIN), where it has one, counts
            too: the higher of the two wins. A waypoint that keeps the altitude (down omitted / NaN) passes.
        max_distance_m: ... or one horizontally further than this from the vehicle [m]; 0 = no limit.
    """

    north_m: float | None = None
    east_m: float | None = None
    down_m: float | None = None
    route: str = ""
    adopt_autopilot_target: bool = False
    adopt_tolerance_m: float = 1.0
    fly_after_restart: bool = False
    max_altitude_m: float = 120.0
    min_altitude_m: float = 1.0
    max_distance_m: float = 2000.0

    def __post_init__(self) -> None:
        if (self.north_m is None) != (self.east_m is None):
            raise _fail("goal.north_m/goal.east_m", "both set or both omitted", (self.north_m, self.east_m))
        if self.route and self.north_m is not None:
            raise _fail("goal.route", "omitted when goal.north_m/east_m are set (one goal source)", self.route)
        if self.down_m is not None and self.north_m is None:
            raise _fail("goal.down_m", "set only together with goal.north_m and goal.east_m", self.down_m)
        for key in ("north_m", "east_m", "down_m"):
            value = getattr(self, key)
            if value is not None:
                _check_range(f"goal.{key}", value, -1e6, 1e6)
        _check_range("goal.adopt_tolerance_m", self.adopt_tolerance_m, 0.1, 50.0)
        _check_range("goal.max_altitude_m", self.max_altitude_m, 0.0, 10_000.0)
        _check_range("goal.min_altitude_m", self.min_altitude_m, *MIN_ALTITUDE_RANGE_M)
        if self.max_altitude_m > 0.0 and self.min_altitude_m >= self.max_altitude_m:
            # else every goal is refused
            raise _fail("goal.min_altitude_m", "less than goal.max_altitude_m unless that is 0", self.min_altitude_m)
        _check_range("goal.max_distance_m", self.max_distance_m, 0.0, 1e6)


@dataclass(frozen=True, slots=True, kw_only=True)
class SensorsConfig:
    """``[sensors]``: where obstacle ranges come from and how long they are remembered.

    Attributes:
        mavlink: Read OBSTACLE_DISTANCE, DISTANCE_SENSOR and OBSTACLE_DISTANCE_3D from the autopilot link.
        zenoh: Read the zenoh sensor topic (needs ``[zenoh] enabled``).
        require_ranges: Ranges must be fresh to navigate (False: pose alone suffices; tests, no sensor).
        memory_expiry_s: Remembered obstacle points are forgotten after this [s].
        merge_radius_m: Points closer than this are merged into one [m].
        max_points: Upper bound on remembered points (oldest dropped first).
        max_range_m: Readings beyond this are ignored (clip to the planner's world) [m].
        surface_fill: Add obstacle points along the chord between adjacent sector returns that lie on one
            straight surface (closes the gaps that one point per sector leaves along an oblique wall; see
            docs/perception.md, "Closing walls between sectors").
        surface_fill_spacing_m: Largest distance between filled points [m] (keep it <= merge_radius_m).
        surface_fill_max_gap_m: Longest chord between two returns that is filled [m].
        surface_fill_line_tol_m: The returns on both sides of a chord must lie this close to its line [m].
        mavlink_sources: Range sensors, besides the autopilot, whose OBSTACLE_DISTANCE / DISTANCE_SENSOR /
            OBSTACLE_DISTANCE_3D are read, as ``"SYSID/COMPID"`` (e.g. ``"1/158"`` for ``apf-sim sensor``); ranges
            from any other source are rejected and counted (``rejected_ranges``).
        forward_obstacle_distance: Send the remembered obstacles around the vehicle to the autopilot as
            OBSTACLE_DISTANCE (72 sectors of 5 deg, body FRD, cm) from our component id, for ArduPilot's proximity
            library (PRX1_TYPE = 2) and the ground station's proximity view. While on, the autopilot's own
            DISTANCE_SENSOR echo of its proximity sectors (ids 10-18) is not read back, nor, on PX4, its own
            OBSTACLE_DISTANCE (its collision-prevention map, which holds ours).
        forward_rate_hz: OBSTACLE_DISTANCE messages per second when forwarding [Hz].
        obstacle_distance_frame: How OBSTACLE_DISTANCE's ``frame`` is read. "as_sent": as PX4 reads them (BODY_FRD
            12 counts from the nose; 0 = MAV_FRAME_GLOBAL, the other GLOBAL* and LOCAL_NED 1 from north; any other
            frame, LOCAL_FRD 20 too, is refused and counted). "body_frd": every frame counts from the nose, as ArduPilot
            reads them (AP_Proximity_MAV.cpp ignores ``frame``): for sensor scripts written for ArduPilot, which leave
            frame at 0. A frame-0 message read as sent is counted (``obstacle_distance_frame_global``) and logged once.
        obstacle_distance_mount_yaw_deg: Added to every OBSTACLE_DISTANCE bearing read from the nose: the sensor's
            forward axis, clockwise from the vehicle's nose seen from above (180 = facing the tail). ArduPilot's
            PRX1_YAW_CORR: set the same value the autopilot uses. Not applied to north-aligned frames [deg].
        laserscan_mount_yaw_deg: The zenoh LaserScan sensor's forward axis (its x), clockwise from the vehicle's nose
            seen from above (180 = facing the tail). The sensor must be level with z up. ``apf.range_scan/1`` JSON
            states its own frame and is not turned [deg].
    """

    mavlink: bool = True
    zenoh: bool = False
    require_ranges: bool = True
    memory_expiry_s: float = 10.0
    merge_radius_m: float = 0.2
    max_points: int = 2000
    max_range_m: float = 8.0
    surface_fill: bool = True
    surface_fill_spacing_m: float = 0.2
    surface_fill_max_gap_m: float = 1.5
    surface_fill_line_tol_m: float = 0.05
    mavlink_sources: tuple[str, ...] = ()
    forward_obstacle_distance: bool = False
    forward_rate_hz: float = 10.0
    obstacle_distance_frame: str = "as_sent"
    obstacle_distance_mount_yaw_deg: float = 0.0
    laserscan_mount_yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.obstacle_distance_frame not in OBSTACLE_DISTANCE_FRAMES:
            raise _fail("sensors.obstacle_distance_frame", "'as_sent' or 'body_frd'", self.obstacle_distance_frame)
        _check_range("sensors.obstacle_distance_mount_yaw_deg", self.obstacle_distance_mount_yaw_deg, -180.0, 180.0)
        _check_range("sensors.laserscan_mount_yaw_deg", self.laserscan_mount_yaw_deg, -180.0, 180.0)
        _check_range("sensors.memory_expiry_s", self.memory_expiry_s, 0.1, 3600.0)
        _check_range("sensors.merge_radius_m", self.merge_radius_m, 0.0, 5.0)
        if not isinstance(self.max_points, int) or not 10 <= self.max_points <= 1_000_000:
            raise _fail("sensors.max_points", "an integer in [10, 1000000]", self.max_points)
        _check_range("sensors.max_range_m", self.max_range_m, 0.1, 1000.0)
        _check_range("sensors.surface_fill_spacing_m", self.surface_fill_spacing_m, 0.01, 5.0)
        _check_range("sensors.surface_fill_max_gap_m", self.surface_fill_max_gap_m, 0.01, 5.0)
        _check_range("sensors.surface_fill_line_tol_m", self.surface_fill_line_tol_m, 0.0, 1.0)
        for text in self.mavlink_sources:
            parse_source("sensors.mavlink_sources[]", text)
        if self.mavlink_sources and not self.mavlink:
            raise _fail("sensors.mavlink_sources", "empty unless sensors.mavlink is true", list(self.mavlink_sources))
        # ArduPilot's proximity backend times out after 0.5 s without a message (AP_Proximity_MAV.cpp)
        _check_range("sensors.forward_rate_hz", self.forward_rate_hz, 2.5, 50.0)

    def source_ids(self) -> tuple[tuple[int, int], ...]:
        """``mavlink_sources`` as (system, component) pairs."""
        return tuple(parse_source("sensors.mavlink_sources[]", text) for text in self.mavlink_sources)


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohSection:
    """``[zenoh]``: the zenoh session (sensor topic in, goal commands in, status out).

    Attributes:
        enabled: Open a zenoh session at all.
        mode: "peer", "client" (to a zenohd router) or "router" (self-contained, no zenohd needed).
        connect: Endpoints to connect to, explicit ``tcp/HOST:PORT`` (or ``tls/HOST:PORT`` with ``config_file``).
        listen: Endpoints to listen on, explicit ``tcp/HOST:PORT`` (or ``tls/``). Multicast scouting is always off.
        config_file: zenoh JSON5 file for TLS certificates / authentication (``deploy/zenoh-companion-tls.json5``),
            relative to this config's directory; it may not set mode, endpoints or multicast scouting. "" = none.
        sensor_key: Key of the range topic (JSON ``apf.range_scan/1`` or ROS 2 LaserScan CDR, told apart by
            the sample's encoding when it is application/json or application/cdr, else by the payload's first byte:
            ROS 2 bridges publish with the default zenoh/bytes). Matched exactly (no wildcards).
        goal_key: Key of the goal command topic (JSON ``apf.goal/1``).
        status_key: Key the status JSON is published on.
        status_rate_hz: Status publications per second [Hz].
        router_wait_s: Client mode: how long to keep trying to reach the router at start (a doubling backoff of
            0.5 to 5 s, one WARNING ``zenoh.router_unreachable`` at the first failure, then at most every 30 s)
            before the service stops with an error (exit 1; systemd's ``Restart=on-failure`` starts it again);
            0 = one attempt [s].
    """

    enabled: bool = False
    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str = ""
    sensor_key: str = "apf/sensors/range0/ranges"
    goal_key: str = "apf/cmd/goal"
    status_key: str = "apf/status"
    status_rate_hz: float = 5.0
    router_wait_s: float = 60.0

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise _fail("zenoh.mode", "'peer', 'client' or 'router'", self.mode)
        for key, endpoints in (("zenoh.connect", self.connect), ("zenoh.listen", self.listen)):
            for ep in endpoints:
                if not isinstance(ep, str) or not ep.startswith(("tcp/", "tls/")) or ":" not in ep:
                    raise _fail(f"{key}[]", "an explicit endpoint 'tcp/HOST:PORT' or 'tls/HOST:PORT'", ep)
        if self.enabled and not (self.connect or self.listen):
            raise _fail("zenoh.connect/zenoh.listen", "at least one endpoint when zenoh.enabled", [])
        for key in ("sensor_key", "goal_key", "status_key"):
            value = getattr(self, key)
            if not value or value.startswith("/") or value.endswith("/"):
                raise _fail(f"zenoh.{key}", "a key expression like 'apf/status' (no leading/trailing /)", value)
        _check_range("zenoh.status_rate_hz", self.status_rate_hz, 0.1, 50.0)
        _check_range("zenoh.router_wait_s", self.router_wait_s, 0.0, 3600.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class StatusConfig:
    """``[status]``: what the service reports to the ground station.

    Attributes:
        named_value_rate_hz: NAMED_VALUE_FLOAT (goal distance, nearest obstacle) per second; 0 = off [Hz].
        statustext: Send STATUSTEXT on every state change.
    """

    named_value_rate_hz: float = 2.0
    statustext: bool = True

    def __post_init__(self) -> None:
        _check_range("status.named_value_rate_hz", self.named_value_rate_hz, 0.0, 50.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class VisualisationConfig:
    """``[visualisation]``: the cycle in Foxglove, live and recorded (docs/visualisation.md; needs the ``viz`` extra).

    Attributes:
        foxglove: Serve a Foxglove WebSocket on 127.0.0.1 (``apf-companion run --foxglove``).
        foxglove_port: Its port; 0 = any free port (logged as ``viz.open``).
        mcap_dir: Write one MCAP recording per run into this directory (``apf-YYYYmmddTHHMMSSZ.mcap``), relative
            to this config's directory; "" = no recording.
    """

    foxglove: bool = False
    foxglove_port: int = 8765
    mcap_dir: str = ""

    def __post_init__(self) -> None:
        if not 0 <= self.foxglove_port <= 65535:
            raise _fail("visualisation.foxglove_port", "in [0, 65535] (0 = any free port)", self.foxglove_port)

    @property
    def enabled(self) -> bool:
        """Any output asked for."""
        return self.foxglove or bool(self.mcap_dir)


@dataclass(frozen=True, slots=True, kw_only=True)
class SafetyConfig:
    """``[safety]``: the hardening gates and limits (docs/hardening.md).

    Attributes:
        max_speed_m_s: A pose further from the last one than this speed allows is rejected [m/s].
        max_accel_m_s2: ... or further than the last velocity plus this acceleration allows [m/s^2].
        pose_noise_m: Position noise allowed on top of the motion limits [m].
        max_abs_position_m: A pose coordinate beyond this (from the EKF origin) is rejected [m].
        pose_time_jump_s: A pose stamped this much further ahead than the receive clock allows (the clock
            relation tracked over the stream) is rejected; poses stamped ahead gain at most this much in all [s].
        pose_reset_samples: Consistent rejected poses in a row that re-anchor (a real EKF reset).
        reset_hold_s: After a re-anchor, hold this long (and announce it) before navigating [s].
        guid_timeout_s: How long the autopilot keeps following the last setpoint's velocity when the setpoints
            stop (ArduCopter GUID_TIMEOUT, default 3 s) [s].
        silent_drift_m: The most the last setpoint may carry the vehicle past its position if nothing follows:
            the velocity feed-forward is at most this over ``guid_timeout_s`` [m].
        clear_scans: Scans from the sensor that saw a remembered obstacle that must see through it, in a row,
            before it is forgotten.
        clear_span_s: ... and those scans must span at least this long (a flood of scans is one piece of
            evidence) [s].
        sectors: Directions (equal azimuth sectors) whose freshness is tracked; 0 = off.
        sector_max_age_s: A sector without a reading for this long is unknown: no motion towards it [s].
        brake_accel_m_s2: The autopilot's horizontal braking acceleration, for the braking envelope
            (apf_companion.envelope; docs/hardening.md "Tracking margin"): ArduCopter WPNAV_ACCEL / 100 (default
            250 cm/s^2, libraries/AC_WPNav/AC_WPNav.cpp), PX4 MPC_ACC_HOR; 0 = off [m/s^2].
        brake_latency_s: Reaction time before that braking: a cycle, the link, the jerk-limited build-up
            (WPNAV_ACCEL / PSC_JERK_XY / 2 = 0.25 s) and the attitude lag (ATC_INPUT_TC 0.15 s) [s].
        resume_after_link_lost: When the autopilot's heartbeat returns, fly on to the goal (only in GUIDED /
            OFFBOARD, with fresh inputs); False: hold and wait for a new goal.
        caution_min_scale: Fewer setpoints, more caution: on a lossy link each setpoint reaches only a fraction
            of a planner step ahead, and its feed-forward speed and silent drift shrink by that fraction; this is
            the smallest fraction; 1 = off.
        caution_full_loss: Pose loss share (poses the autopilot sent that did not arrive) or setpoint send
            failure share at which the fraction reaches ``caution_min_scale`` (linear from 1 at no loss).
        caution_ok_age_s: A pose up to this old when the cycle runs costs no caution; older poses lower the
            fraction linearly down to ``caution_min_scale`` at ``cycle.pose_max_age_s`` [s].
        caution_window_s: Pose loss and send failures are measured over this long [s].
    """

    max_speed_m_s: float = 15.0
    max_accel_m_s2: float = 10.0
    pose_noise_m: float = 0.3
    max_abs_position_m: float = 10_000.0
    pose_time_jump_s: float = 1.0
    pose_reset_samples: int = 10
    reset_hold_s: float = 2.0
    guid_timeout_s: float = 3.0
    silent_drift_m: float = 1.0
    clear_scans: int = 3
    clear_span_s: float = 0.3
    sectors: int = 16
    sector_max_age_s: float = 1.0
    brake_accel_m_s2: float = 2.5
    brake_latency_s: float = 0.5
    resume_after_link_lost: bool = True
    caution_min_scale: float = 0.5
    caution_full_loss: float = 0.5
    caution_ok_age_s: float = 0.2
    caution_window_s: float = 2.0

    def __post_init__(self) -> None:
        _check_range("safety.caution_min_scale", self.caution_min_scale, 0.0, 1.0, lo_open=True)
        _check_range("safety.caution_full_loss", self.caution_full_loss, 0.0, 1.0, lo_open=True)
        _check_range("safety.caution_ok_age_s", self.caution_ok_age_s, 0.0, 10.0)
        _check_range("safety.caution_window_s", self.caution_window_s, 0.1, 60.0)
        _check_range("safety.max_speed_m_s", self.max_speed_m_s, 0.1, 100.0)
        _check_range("safety.max_accel_m_s2", self.max_accel_m_s2, 0.1, 100.0)
        _check_range("safety.pose_noise_m", self.pose_noise_m, 0.0, 10.0)
        _check_range("safety.max_abs_position_m", self.max_abs_position_m, 10.0, 1e7)
        _check_range("safety.pose_time_jump_s", self.pose_time_jump_s, 0.05, 60.0)
        if not isinstance(self.pose_reset_samples, int) or not 2 <= self.pose_reset_samples <= 1000:
            raise _fail("safety.pose_reset_samples", "an integer in [2, 1000]", self.pose_reset_samples)
        _check_range("safety.reset_hold_s", self.reset_hold_s, 0.0, 60.0)
        _check_range("safety.guid_timeout_s", self.guid_timeout_s, 0.1, 60.0)
        _check_range("safety.silent_drift_m", self.silent_drift_m, 0.0, 10.0)
        if not isinstance(self.clear_scans, int) or not 1 <= self.clear_scans <= 100:
            raise _fail("safety.clear_scans", "an integer in [1, 100]", self.clear_scans)
        if not isinstance(self.sectors, int) or not (self.sectors == 0 or 4 <= self.sectors <= 360):
            raise _fail("safety.sectors", "0 or an integer in [4, 360]", self.sectors)
        _check_range("safety.clear_span_s", self.clear_span_s, 0.0, 60.0)
        _check_range("safety.sector_max_age_s", self.sector_max_age_s, 0.05, 60.0)
        _check_range("safety.brake_accel_m_s2", self.brake_accel_m_s2, 0.0, 20.0)
        _check_range("safety.brake_latency_s", self.brake_latency_s, 0.0, 5.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class ServiceConfig:
    """The whole configuration (top-level keys plus one section per table).

    Attributes:
        dry_run: Plan and log only; send nothing on any link.
        exit_when_done: Exit when the flight ends (ARRIVED at the last waypoint, or STUCK): for scripted
            simulated flights (``apf-sim fly``).
        max_flight_s: With ``exit_when_done``: give up (exit, outcome timeout, or link_lost when it comes in
            LINK_LOST) after this many vehicle seconds of flight (from the first navigation setpoint; from the goal
            when navigation never started: a run stuck waiting for position, ranges or the takeover ends too);
            0 = no limit [s].
        max_link_lost_s: With ``exit_when_done``: no autopilot HEARTBEAT for this long (counted from the last one,
            so it includes ``link.heartbeat_timeout_s``, or from the start when the autopilot was never heard) ends
            the run with outcome link_lost (exit code 3), also while the goal is kept for the heartbeat's return
            (``safety.resume_after_link_lost``); 0 = wait for ever [s].
    """

    dry_run: bool = False
    exit_when_done: bool = False
    max_flight_s: float = 0.0
    max_link_lost_s: float = 60.0
    link: LinkConfig = field(default_factory=LinkConfig)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    cycle: CycleConfig = field(default_factory=CycleConfig)
    goal: GoalConfig = field(default_factory=GoalConfig)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    zenoh: ZenohSection = field(default_factory=ZenohSection)
    status: StatusConfig = field(default_factory=StatusConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    visualisation: VisualisationConfig = field(default_factory=VisualisationConfig)
    base_dir: Path = field(default_factory=Path.cwd)
    """Directory relative paths (goal.route, link.tlog) are resolved against (the config file's)."""

    def __post_init__(self) -> None:
        _check_range("max_flight_s", self.max_flight_s, *MAX_FLIGHT_RANGE_S)
        _check_range("max_link_lost_s", self.max_link_lost_s, *MAX_LINK_LOST_RANGE_S)
        if 0.0 < self.max_link_lost_s < self.link.heartbeat_timeout_s:
            raise _fail("max_link_lost_s", "0 or at least link.heartbeat_timeout_s", self.max_link_lost_s)
        if self.sensors.zenoh and not self.zenoh.enabled:
            raise _fail("sensors.zenoh", "false unless zenoh.enabled is true", True)
        lc = self.link
        ours = ((lc.autopilot_sysid, lc.component_id), (lc.autopilot_sysid, lc.autopilot_compid))
        for system, component in self.sensors.source_ids():
            if (system, component) in ours:
                raise _fail("sensors.mavlink_sources[]", "not our own or the autopilot's ids", f"{system}/{component}")
        if self.safety.caution_ok_age_s >= self.cycle.pose_max_age_s:
            raise _fail("safety.caution_ok_age_s", "less than cycle.pose_max_age_s", self.safety.caution_ok_age_s)

    def resolve(self, path: str) -> Path:
        """A path from the config, relative to ``base_dir``."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else self.base_dir / p


# ---------------------------------------------------------------------------------------------------------------
# Loading: strict type checks per field, typo suggestions, then the dataclasses validate ranges.

_SECTIONS: dict[str, type[Any]] = {
    "link": LinkConfig,
    "autopilot": AutopilotConfig,
    "planner": PlannerConfig,
    "cycle": CycleConfig,
    "goal": GoalConfig,
    "sensors": SensorsConfig,
    "zenoh": ZenohSection,
    "status": StatusConfig,
    "safety": SafetyConfig,
    "visualisation": VisualisationConfig,
}
_TOP_LEVEL = ("dry_run", "exit_when_done", "max_flight_s", "max_link_lost_s")


def did_you_mean(key: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'name'?"`` when the last part of ``key`` is close to one of ``choices`` (a typo), else
    ``""``: the hint of every unknown-key error (config keys and ``[planner.params]``)."""
    close = difflib.get_close_matches(key.split(".")[-1], list(choices), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def _unknown_key(key: str, choices: list[str]) -> ConfigError:
    hint = did_you_mean(key, choices)
    return ConfigError(f"unknown config key {key!r}{hint} (allowed: {', '.join(sorted(choices))})")


def _coerce(key: str, value: Any, annotation: str) -> Any:
    """Check a TOML value against a field's annotation (a string: ``from __future__ import annotations``)."""
    ann = annotation.replace(" ", "")
    if ann == "bool":
        if not isinstance(value, bool):
            raise _fail(key, "true or false", value)
        return value
    if ann == "int":
        if not isinstance(value, int) or isinstance(value, bool):
            raise _fail(key, "an integer", value)
        return value
    if ann in ("float", "float|None"):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise _fail(key, "a number", value)
        return float(value)
    if ann == "str":
        if not isinstance(value, str):
            raise _fail(key, "a string", value)
        return value
    if ann in ("tuple[int,...]", "tuple[str,...]"):
        item = int if "int" in ann else str
        if not isinstance(value, list) or not all(isinstance(v, item) and not isinstance(v, bool) for v in value):
            raise _fail(key, f"a list of {item.__name__}", value)
        return tuple(value)
    if ann == "Autopilot":
        try:
            return Autopilot(value)
        except ValueError as err:
            allowed = ", ".join(repr(a.value) for a in Autopilot)
            raise _fail(key, f"one of {allowed}", value) from err
    if ann.startswith("Mapping["):
        if not isinstance(value, dict):
            raise _fail(key, "a table", value)
        for sub_key, sub_value in value.items():
            # Nested lists of numbers are vector parameters (planner.params.nav_area_ne_m: a rectangle or a polygon's
            # vertices; nav_keepout_ne_m: polygons); the planner checks their shape.
            if isinstance(sub_value, dict) or (isinstance(sub_value, list) and not _numbers(sub_value, depth=3)):
                allowed = "a number, string, boolean, or a list of numbers (or of such lists, three deep at most)"
                raise _fail(f"{key}.{sub_key}", allowed, sub_value)
        return dict(value)
    msg = f"internal: no coercion for {key} ({annotation})"
    raise AssertionError(msg)


def _numbers(values: list[Any], depth: int) -> bool:
    """Whether ``values`` is a list of numbers (a bool is not), or of such lists, at most ``depth`` lists deep."""
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return True
    return depth > 1 and all(isinstance(v, list) and _numbers(v, depth - 1) for v in values)


def _own_error(prefix: str, err: ConfigError) -> bool:
    """``err`` is about the key ``prefix`` itself (``link.connect``, ``link.gcs_sysids[]``), not a cross-key rule."""
    text = str(err)
    return text.startswith(prefix) and not (
        text[len(prefix) : len(prefix) + 1].isalnum() or text[len(prefix) :][:1] in "_/"
    )


def _build_section(name: str, cls: type[Any], table: Any, errors: list[ConfigError]) -> Any:
    """The section's dataclass, or None with every error found appended to ``errors``: unknown keys and type
    errors key by key, then range errors (each key checked alone when the whole section fails, so that all of
    them are reported, not only the first)."""
    if not isinstance(table, dict):
        errors.append(_fail(name, "a table", table))
        return None
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    n_before = len(errors)
    for key, value in table.items():
        try:
            if key not in fields:
                raise _unknown_key(f"{name}.{key}", list(fields))
            kwargs[key] = _coerce(f"{name}.{key}", value, str(fields[key].type))
        except ConfigError as err:
            errors.append(err)
    try:
        section = cls(**kwargs)
    except ConfigError as whole:
        alone: list[ConfigError] = []
        for key, value in kwargs.items():
            try:
                cls(**{key: value})
            except ConfigError as err:
                if _own_error(f"{name}.{key}", err):
                    alone.append(err)
        errors.extend(alone or [whole])
        return None
    return section if len(errors) == n_before else None


def config_from_mapping(data: Mapping[str, Any], *, base_dir: Path | None = None) -> ServiceConfig:
    """Build and validate a ServiceConfig from parsed TOML (a nested dict).

    Raises:
        ConfigError: naming the offending key and the allowed values; with several errors, all of them (one
            per line), so a file is fixed in one pass.
    """
    kwargs: dict[str, Any] = {}
    errors: list[ConfigError] = []
    for key, value in data.items():
        try:
            if key in _SECTIONS:
                kwargs[key] = _build_section(key, _SECTIONS[key], value, errors)
            elif key in _TOP_LEVEL:
                ann = "bool" if key in ("dry_run", "exit_when_done") else "float"
                kwargs[key] = _coerce(key, value, ann)
            else:
                raise _unknown_key(key, [*_SECTIONS, *_TOP_LEVEL])
        except ConfigError as err:
            errors.append(err)
    if base_dir is not None:
        kwargs["base_dir"] = base_dir
    if not errors:
        try:
            return ServiceConfig(**kwargs)
        except ConfigError as err:
            errors.append(err)
    if len(errors) == 1:
        raise errors[0]
    lines = "\n".join(f"  - {e}" for e in errors)
    msg = f"{len(errors)} config errors:\n{lines}"
    raise ConfigError(msg)


def load_config(path: Path | str) -> ServiceConfig:
    """Read and validate one TOML config file; relative paths inside it resolve against its directory.

    Raises:
        ConfigError: the file is missing or not TOML, or a key is unknown, mistyped or out of range.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        msg = f"cannot read config file {p}: {err.strerror}"
        raise ConfigError(msg) from err
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        msg = f"config file {p} is not valid TOML: {err}"
        raise ConfigError(msg) from err
    return config_from_mapping(data, base_dir=p.resolve().parent)
