"""The simulated range sensor: a horizontal 360-degree scanner ray-cast into the world.

Each sector reads the exact range to the nearest obstacle surface anywhere inside its angular window (not just
along its centre ray), like a sector-binned lidar, so the paper's zero-radius point obstacles are seen too.
Sector ``i`` is centred on ``angle_offset_deg + i * increment_deg`` clockwise from the body's forward axis
(body FRD) and spans half an increment either side.

Readings (metres): finite = obstacle, +inf = nothing up to ``max_range_m``, NaN = unknown (a dropout, or a
sector beyond the configured count). Noise is additive Gaussian on finite readings, clipped at 0.

Encodings (MAVLink, all from these readings):
- OBSTACLE_DISTANCE: ``distances`` in cm, frame MAV_FRAME_BODY_FRD, ``increment_f`` and ``angle_offset`` set
  (``increment`` too, rounded, for old readers); UINT16_MAX = unknown, ``max_distance + 1`` = free; readings
  below ``min_distance`` are sent as measured (the receiver discards them as invalid).
- DISTANCE_SENSOR: 8 messages, orientation MAV_SENSOR_ROTATION_NONE..YAW_315 (= ids 0..7), each the minimum
  over its 45-degree window; free = ``max_distance + 1``; a dropout sends nothing for that orientation.
- OBSTACLE_DISTANCE_3D: one message per obstacle in range: its nearest surface point in body FRD [m], the
  obstacle id = its index in the world (circles, then walls); all of one scan share ``time_boot_ms``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from sim.world.model import FloatArray, World

__all__ = [
    "SENSOR_MESSAGES",
    "RangeSensorConfig",
    "Scan",
    "distance_sensor_msgs",
    "obstacle_distance_3d_msgs",
    "obstacle_distance_msg",
    "scan_world",
]

UINT16_MAX = 65535
MAV_FRAME_BODY_FRD = 12
MAV_DISTANCE_SENSOR_LASER = 0
SENSOR_MESSAGES = frozenset({"obstacle_distance", "distance_sensor", "obstacle_distance_3d"})
_OCTANTS_RAD = np.deg2rad(45.0 * np.arange(8))


@dataclass(frozen=True, slots=True, kw_only=True)
class RangeSensorConfig:
    """Geometry and output of the range sensor (noise, range and rate are SIM_RNG_* parameters).

    Attributes:
        sectors: number of sectors used (<= 72); the rest of OBSTACLE_DISTANCE is UINT16_MAX.
        increment_deg: sector width [deg].
        angle_offset_deg: body bearing of sector 0's centre, clockwise from forward [deg].
        messages: which MAVLink messages to emit: any of ``obstacle_distance``, ``distance_sensor``,
            ``obstacle_distance_3d``.
        links: indices of the links that get sensor messages (None = all).
    """

    sectors: int = 72
    increment_deg: float = 5.0
    angle_offset_deg: float = 0.0
    messages: frozenset[str] = frozenset({"obstacle_distance"})
    links: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if not 1 <= self.sectors <= 72:
            msg = f"sensor.sectors must be in [1, 72], got {self.sectors}"
            raise ConfigError(msg)
        if not 0.5 <= self.increment_deg <= 120.0 or self.sectors * self.increment_deg > 360.0 + 1e-9:
            msg = f"sensor.increment_deg must be in [0.5, 120] with sectors*increment <= 360, got {self.increment_deg}"
            raise ConfigError(msg)
        if not math.isfinite(self.angle_offset_deg):
            raise ConfigError("sensor.angle_offset_deg must be finite")
        unknown = set(self.messages) - SENSOR_MESSAGES
        if unknown:
            msg = f"sensor.messages: unknown {sorted(unknown)}; allowed {sorted(SENSOR_MESSAGES)}"
            raise ConfigError(msg)

    def body_bearings_rad(self) -> FloatArray:
        """(sectors,) sector centre bearings in body FRD, clockwise from forward [rad]."""
        return np.asarray(
            np.deg2rad(self.angle_offset_deg + self.increment_deg * np.arange(self.sectors)), dtype=np.float64
        )


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Scan:
    """One sensor sweep taken at ``t_s`` (simulated seconds since boot)."""

    t_s: float
    pos_ned_m: FloatArray
    yaw_rad: float
    bearings_body_rad: FloatArray
    ranges_m: FloatArray  # finite = obstacle, inf = free, nan = unknown
    min_range_m: float
    max_range_m: float
    octant_ranges_m: FloatArray  # (8,) DISTANCE_SENSOR windows, same conventions
    points_body_frd_m: FloatArray  # (K, 3) nearest point of each obstacle in range, body FRD
    point_ids: npt.NDArray[np.intp]  # (K,) obstacle ids


def _add_noise(
    ranges: FloatArray, octants_r: FloatArray, pts_body: FloatArray, noise_sd_m: float, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gaussian range noise on sectors, octants and points (points keep their bearing); never below 0."""
    ranges = ranges + rng.normal(0.0, noise_sd_m, ranges.shape)
    octants_r = octants_r + rng.normal(0.0, noise_sd_m, octants_r.shape)
    d = np.hypot(pts_body[:, 0], pts_body[:, 1])
    d_noisy = np.maximum(d + rng.normal(0.0, noise_sd_m, d.shape), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(d > 0, d_noisy / d, 1.0)
    pts_body = pts_body * scale[:, None]
    ranges = np.where(np.isfinite(ranges), np.maximum(ranges, 0.0), ranges)
    octants_r = np.where(np.isfinite(octants_r), np.maximum(octants_r, 0.0), octants_r)
    return ranges, octants_r, pts_body


def scan_world(
    world: World,
    cfg: RangeSensorConfig,
    *,
    t_s: float,
    pos_ned_m: FloatArray,
    yaw_rad: float,
    min_range_m: float,
    max_range_m: float,
    noise_sd_m: float,
    dropout_prob: float,
    rng: np.random.Generator,
    octants: bool = True,
    points: bool = True,
) -> Scan:
    """Sweep the sensor from a pose; sectors, and optionally the 8 octants and the nearest point of each obstacle
    in range (for DISTANCE_SENSOR and OBSTACLE_DISTANCE_3D), all vectorised."""
    alt = -float(pos_ned_m[2])
    pos_ne = pos_ned_m[:2]
    body = cfg.body_bearings_rad()
    half = math.radians(cfg.increment_deg) / 2.0
    ranges = world.window_ranges_m(pos_ne, body + yaw_rad, half, alt_m=alt)
    if octants:
        oct_r = world.window_ranges_m(pos_ne, _OCTANTS_RAD + yaw_rad, math.radians(22.5), alt_m=alt)
    else:
        oct_r = np.full(8, np.nan)
    if points and world.n_obstacles:
        pts_ne, dists = world.nearest_points_ne_m(pos_ne, alt)
    else:
        pts_ne, dists = np.zeros((0, 2)), np.zeros(0)
    sel = np.flatnonzero(dists <= max_range_m)
    rel = pts_ne[sel] - pos_ne
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    pts_body = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], np.zeros(sel.size)], axis=1)
    octants_r = oct_r
    if noise_sd_m > 0:
        ranges, octants_r, pts_body = _add_noise(ranges, octants_r, pts_body, noise_sd_m, rng)
    ranges = np.where(ranges > max_range_m, np.inf, ranges)
    octants_r = np.where(octants_r > max_range_m, np.inf, octants_r)
    ids = sel
    if dropout_prob > 0:
        ranges = np.where(rng.random(ranges.shape) < dropout_prob, np.nan, ranges)
        octants_r = np.where(rng.random(octants_r.shape) < dropout_prob, np.nan, octants_r)
        keep = rng.random(sel.shape) >= dropout_prob
        pts_body, ids = pts_body[keep], sel[keep]
    return Scan(
        t_s=t_s,
        pos_ned_m=pos_ned_m.copy(),
        yaw_rad=yaw_rad,
        bearings_body_rad=body,
        ranges_m=ranges,
        min_range_m=min_range_m,
        max_range_m=max_range_m,
        octant_ranges_m=octants_r,
        points_body_frd_m=pts_body,
        point_ids=ids,
    )


def _to_cm(ranges_m: FloatArray, max_cm: int) -> list[int]:
    cm = np.full(ranges_m.shape, UINT16_MAX, dtype=np.int64)
    finite = np.isfinite(ranges_m)
    cm[finite] = np.minimum(np.rint(ranges_m[finite] * 100.0), max_cm).astype(np.int64)
    cm[np.isposinf(ranges_m)] = max_cm + 1
    return [int(x) for x in cm]


def obstacle_distance_msg(mav: Any, scan: Scan, cfg: RangeSensorConfig) -> Any:
    """OBSTACLE_DISTANCE (330) for a scan."""
    max_cm = round(scan.max_range_m * 100.0)
    dist = _to_cm(scan.ranges_m, max_cm) + [UINT16_MAX] * (72 - cfg.sectors)
    return mav.obstacle_distance_encode(
        int(scan.t_s * 1e6),
        MAV_DISTANCE_SENSOR_LASER,
        dist,
        max(1, min(255, round(cfg.increment_deg))),
        round(scan.min_range_m * 100.0),
        max_cm,
        increment_f=float(cfg.increment_deg),
        angle_offset=float(cfg.angle_offset_deg),
        frame=MAV_FRAME_BODY_FRD,
    )


def distance_sensor_msgs(mav: Any, scan: Scan) -> list[Any]:
    """DISTANCE_SENSOR (132), one per horizontal orientation 0..7 (YAW_0..YAW_315) that has a reading."""
    max_cm = round(scan.max_range_m * 100.0)
    cms = _to_cm(scan.octant_ranges_m, max_cm)
    out = []
    for k, cm in enumerate(cms):
        if cm == UINT16_MAX:
            continue  # dropout: no message
        out.append(
            mav.distance_sensor_encode(
                int(scan.t_s * 1000) & 0xFFFFFFFF,
                round(scan.min_range_m * 100.0),
                max_cm,
                cm,
                MAV_DISTANCE_SENSOR_LASER,
                k,
                k,
                255,
                horizontal_fov=math.radians(45.0),
                vertical_fov=0.0,
                quaternion=[0.0, 0.0, 0.0, 0.0],
                signal_quality=0,
            )
        )
    return out


def obstacle_distance_3d_msgs(mav: Any, scan: Scan) -> list[Any]:
    """OBSTACLE_DISTANCE_3D (11037), one per obstacle in range, body FRD metres."""
    t_ms = int(scan.t_s * 1000) & 0xFFFFFFFF
    return [
        mav.obstacle_distance_3d_encode(
            t_ms,
            MAV_DISTANCE_SENSOR_LASER,
            MAV_FRAME_BODY_FRD,
            min(int(i), UINT16_MAX - 1),
            float(p[0]),
            float(p[1]),
            float(p[2]),
            float(scan.min_range_m),
            float(scan.max_range_m),
        )
        for p, i in zip(scan.points_body_frd_m, scan.point_ids, strict=True)
    ]
