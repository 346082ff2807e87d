"""The obstacle store: the one writer of the ``ObstacleMemory``, with the azimuth sectors' freshness, where the
sensors look in the body frame (``LookCoverage``) and the time of the newest usable scan. The navigator reads it
through the front end (``points``, ``ranges_t_s``: the ``ObstacleView`` protocol); the scan intake places scans
into it, a re-anchor of the poses empties it (but for the body-frame coverage)."""

from __future__ import annotations

import numpy as np

from apf_companion.perception.coverage import LookCoverage
from apf_companion.perception.frontparams import PerceptionCounters, PerceptionParams
from apf_companion.perception.geometry import element_half_width_rad, scan_bearings_body_rad, scan_bearings_ned_rad
from apf_companion.perception.memory import ObstacleMemory
from apf_companion.perception.sectors import SectorFreshness
from apf_companion.perception.types import FloatArray, Pose, RangeScan

__all__ = ["ObstacleStore"]


class ObstacleStore:
    """Owns the obstacle memory, the sector freshness, the body-frame coverage, the newest usable scan's time and its
    points."""

    def __init__(self, params: PerceptionParams, counters: PerceptionCounters) -> None:
        self.params = params
        self.counters = counters
        self.memory = ObstacleMemory(
            expiry_s=params.memory_expiry_s,
            merge_radius_m=max(params.merge_radius_m, 1e-3),
            max_points=params.max_points,
        )
        self.sectors = SectorFreshness(params.sectors, params.sector_max_age_s)
        # Where the sensors look (body FRD), for the commanded heading; same staleness as the sectors.
        self.coverage = LookCoverage(params.sector_max_age_s)
        self.ranges_t_s: float | None = None  # measurement time of the newest usable scan (service clock)
        #: The obstacle points the newest usable scan added, (M, 3) local NED [m] (read by the visualisation).
        self.latest_scan_ned_m: FloatArray = np.empty((0, 3))

    def observe(self, scan: RangeScan, pose: Pose, points: FloatArray, spread_m: FloatArray, sensor: int) -> None:
        """A scan placed with ``pose``: its beams clear the points they see through (``clear_scans``), its
        directions count as measured, and ``points`` (with how far beside each its surface may lie) are added."""
        p = self.params
        refused = self.memory.clears_refused
        self.memory.clear_observed(scan, pose, sensor=sensor, clear_scans=p.clear_scans, clear_span_s=p.clear_span_s)
        self.counters.clears_refused += self.memory.clears_refused - refused
        usable = ~np.isnan(scan.ranges_m)
        self.sectors.note(scan_bearings_ned_rad(scan, pose)[usable], scan.t_s)
        width = element_half_width_rad(scan.bearings_rad)  # over every element: the sensor's increment
        self.coverage.note(scan_bearings_body_rad(scan, pose)[usable], width, scan.t_s)
        self._add(points, scan.t_s, sensor, spread_m)

    def add_points(self, points: FloatArray, pose: Pose, t_s: float, sensor: int) -> None:
        """Obstacle points seen from ``pose`` at ``t_s`` (OBSTACLE_DISTANCE_3D): their directions count as measured."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        rel = pts - pose.pos_ned_m
        bearings = np.arctan2(rel[:, 1], rel[:, 0])
        self.sectors.note(bearings, t_s)
        self.coverage.note(bearings - pose.yaw_rad, 0.0, t_s)
        self._add(points, t_s, sensor)

    def remember(self, points_ned_m: FloatArray, t_s: float) -> None:
        """Obstacle points already placed in local NED, measured at ``t_s`` (a perfect sensor in tests and
        closed-loop simulations; the service itself feeds scans): every direction counts as measured."""
        self.sectors.note_all(t_s)
        self.coverage.note_all(t_s)
        self._add(points_ned_m, t_s)

    def clear(self) -> None:
        """The poses were re-anchored: the remembered points and readings are in the old frame; forget them. The
        body-frame coverage stays: where a sensor looks does not depend on the local frame."""
        self.memory.clear()
        self.sectors.clear()

    def _add(self, points: FloatArray, t_s: float, sensor: int = -1, spread_m: FloatArray | None = None) -> None:
        """The one write of points to the obstacle memory: a usable scan measured at ``t_s`` (possibly no points:
        all free is news too, it keeps the ranges fresh)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.latest_scan_ned_m = pts
        if pts.shape[0]:
            self.memory.add(pts, t_s, sensor, spread_m)
        if self.ranges_t_s is None or t_s > self.ranges_t_s:
            self.ranges_t_s = t_s
