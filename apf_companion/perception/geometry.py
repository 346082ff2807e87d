"""Placing range scans in local NED, and filling straight surfaces between sector returns.

Surface fill
------------
A sector scan gives one point per sector, so along a wall ``d`` metres away the points spread as
``d * increment / cos^2`` of the angle off abeam: 0.8 m apart 3 m along a wall 0.5 m away with 5-degree
sectors, wide enough for a point-based clearance check to pass through the wall. ``surface_fill_points`` fills
those chords.

Rule ("same surface"), for elements ``i`` and ``j`` of adjacent sectors (bearings one increment apart,
including last -> first in a full-circle scan; see ``_adjacent_steps``) that both have finite ranges:

1. the chord ``|p_j - p_i| <= max_gap_m``, and
2. the returns on BOTH sides, ``p_{i-1}`` and ``p_{j+1}`` (each an adjacent sector with a finite range), lie
   within ``line_tol_m`` of the straight line through ``p_i`` and ``p_j``: four returns in a row on one
   line. A wall is straight over four sectors; separate objects rarely line up that way.

Such a chord gets ``ceil(L / spacing_m) - 1`` points at equal steps, so neighbouring points are at most
``spacing_m`` apart; the returns themselves are not repeated (``scan_to_points_ned`` gives them).

Why both sides: with one collinear neighbour (three returns) a close trunk's two returns, a few centimetres
apart, define almost any line through the next trunk's return. Measured on the simulator's 72 x 5-degree
sensor (minimum range in each 5-degree window) at 300 random free positions per world: with one side, 137
filled points in ``forest-dense`` lay more than 0.3 m from any trunk (in a passable gap); with both sides,
``forest-dense`` got no filled point at all (``benchmarks/replay_surface_fill.py --rules``). Straight-wall
returns deviate at most 1.1 cm from the line through their neighbours, 0.3-2 m from the wall.

Failure modes (filled points are obstacles only; ``ObstacleMemory.clear_observed`` removes them once a later
scan sees through them, so a wrong fill is temporary):

- A real gap narrower than what one sector resolves, between collinear surfaces (a doorway in a wall seen very
  obliquely, objects that happen to line up over four sectors) is closed until a scan sees through it. Such
  a gap was not seen as free by this scan anyway: each sector reports its nearest return.
- The chords at the ends of a straight run stay unfilled: at a wall's end, at a corner between two walls
  (neither side lies on the chord's line), and at the last chord before grazing incidence (a sector nearly
  parallel to the wall returns the window's nearest point, off the line): 0.3 m from a wall the chord 80-85
  degrees off abeam (1.23 m long, 1.7-3 m along the wall) stays open until the vehicle comes nearer.
- Curved surfaces (large trunks, round pillars) and range noise above ``line_tol_m`` leave chords unfilled;
  range noise moves a point mostly along its ray, and on the oblique walls where chords are long that ray
  runs nearly along the wall, so the perpendicular error stays small there.

The helpers work on all pairs at once (pair ``i`` joins element ``i`` and element ``(i + 1) % M``; the
neighbouring pairs come from rolling the arrays): no per-sector Python loop.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.perception.types import FloatArray, Pose, RangeScan, ScanFrame

BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]

__all__ = [
    "element_half_width_rad",
    "return_spread_m",
    "scan_bearings_body_rad",
    "scan_bearings_ned_rad",
    "scan_to_points_ned",
    "surface_fill_points",
]

_STEP_RTOL = 1e-3  # bearing steps within 0.1 % of the scan's increment are "one increment"


def scan_bearings_ned_rad(scan: RangeScan, pose: Pose) -> FloatArray:
    """(M,) bearings of the scan's elements from north, clockwise [rad] (not wrapped).

    BODY_FRD bearings are turned by the vehicle yaw (both are clockwise from above); LOCAL_NED bearings are
    already north-referenced and ignore the pose.
    """
    if scan.frame is ScanFrame.BODY_FRD:
        return np.asarray(scan.bearings_rad + pose.yaw_rad, dtype=np.float64)
    return np.asarray(scan.bearings_rad, dtype=np.float64)


def scan_bearings_body_rad(scan: RangeScan, pose: Pose) -> FloatArray:
    """(M,) bearings of the scan's elements from the nose, clockwise (body FRD) [rad] (not wrapped): a
    LOCAL_NED scan's bearings less the vehicle yaw at its time (``pose``), a BODY_FRD scan's as they are."""
    if scan.frame is ScanFrame.BODY_FRD:
        return np.asarray(scan.bearings_rad, dtype=np.float64)
    return np.asarray(scan.bearings_rad - pose.yaw_rad, dtype=np.float64)


def element_half_width_rad(bearings_rad: FloatArray) -> float:
    """Half the angular width of one scan element: half the median step of the sorted bearings around the circle
    (0 for a single beam, which then clears nothing and places its point with no spread)."""
    b = np.sort(np.mod(bearings_rad, 2.0 * math.pi))
    if b.size < 2:
        return 0.0
    return 0.5 * float(np.median(np.diff(np.concatenate([b, b[:1] + 2.0 * math.pi]))))


def return_spread_m(scan: RangeScan) -> FloatArray:
    """(K,) how far beside each of ``scan_to_points_ned``'s points the surface may lie [m]: a return is the nearest
    surface anywhere in its element's window but is placed on the window's centre, so range x sin(half width)."""
    r = scan.ranges_m[np.isfinite(scan.ranges_m)]
    return np.asarray(r * math.sin(element_half_width_rad(scan.bearings_rad)), dtype=np.float64)


def scan_to_points_ned(scan: RangeScan, pose: Pose) -> FloatArray:
    """Obstacle points of a scan in local NED.

    For each element with a finite range ``r`` at NED bearing ``b`` (see ``scan_bearings_ned_rad``):
    ``north = n0 + r cos b``, ``east = e0 + r sin b``, ``down = d0``, where ``(n0, e0, d0)`` is
    ``pose.pos_ned_m``. The scan is taken as horizontal at the vehicle's height (roll and pitch ignored).
    Free (+inf) and unknown/invalid (NaN) elements give no point.

    Parameters
    ----------
    scan:
        The scan.
    pose:
        The vehicle pose AT THE SCAN'S MEASUREMENT TIME (``PoseHistory.at(scan.t_s)``); using the latest
        pose instead smears obstacles by the distance flown and the yaw turned since the measurement.

    Returns
    -------
    (K, 3) float64 points in local NED [m], K = number of finite ranges, in scan order.
    """
    mask = np.isfinite(scan.ranges_m)
    r = scan.ranges_m[mask]
    b = scan_bearings_ned_rad(scan, pose)[mask]
    points = np.empty((r.size, 3), dtype=np.float64)
    points[:, 0] = pose.pos_ned_m[0] + r * np.cos(b)
    points[:, 1] = pose.pos_ned_m[1] + r * np.sin(b)
    points[:, 2] = pose.pos_ned_m[2]
    return points


def _adjacent_steps(bearings_rad: FloatArray) -> BoolArray:
    """(M,) True where element ``i`` and element ``(i + 1) % M`` are adjacent sectors.

    The increment is the median step between consecutive elements (wrapped to (-pi, pi]); a step counts when it
    equals it (relative tolerance ``_STEP_RTOL``). The last -> first step equals it only when the scan closes the
    full circle (e.g. 72 x 5 degrees). Increments of 90 degrees or more give no adjacent sectors.
    """
    m = bearings_rad.size
    if m < 2:
        return np.zeros(m, dtype=np.bool_)
    steps = np.remainder(np.roll(bearings_rad, -1) - bearings_rad + math.pi, 2.0 * math.pi) - math.pi
    inc = float(np.median(steps[:-1]))
    if not 0.0 < abs(inc) < 0.5 * math.pi:
        return np.zeros(m, dtype=np.bool_)
    return np.asarray(np.abs(steps - inc) <= _STEP_RTOL * abs(inc), dtype=np.bool_)


def _check_fill_params(spacing_m: float, max_gap_m: float, line_tol_m: float) -> None:
    """ConfigError unless spacing_m > 0, max_gap_m > 0 and line_tol_m >= 0, all finite."""
    if not (math.isfinite(spacing_m) and spacing_m > 0.0):
        raise ConfigError(f"surface fill spacing_m must be finite and > 0, got {spacing_m!r}")
    if not (math.isfinite(max_gap_m) and max_gap_m > 0.0):
        raise ConfigError(f"surface fill max_gap_m must be finite and > 0, got {max_gap_m!r}")
    if not (math.isfinite(line_tol_m) and line_tol_m >= 0.0):
        raise ConfigError(f"surface fill line_tol_m must be finite and >= 0, got {line_tol_m!r}")


def _line_deviation_m(unit: FloatArray, offset_m: FloatArray) -> FloatArray:
    """(M,) distance of ``offset_m`` (M, 2), taken from a point on each line, from the line along ``unit``."""
    return np.asarray(np.abs(unit[:, 0] * offset_m[:, 1] - unit[:, 1] * offset_m[:, 0]), dtype=np.float64)


def _same_surface(
    p_m: FloatArray, chord_m: FloatArray, length_m: FloatArray, adj: BoolArray, line_tol_m: float, both_sides: bool
) -> BoolArray:
    """(M,) rule 2 of the module docstring: the neighbouring returns lie on the line of chord ``i``.

    ``p_m`` (M, 2) are the returns relative to the vehicle, ``chord_m`` = p_j - p_i, ``length_m`` its length,
    ``adj`` the pairs of adjacent sectors with finite ranges. ``both_sides`` False accepts one side.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = chord_m / length_m[:, None]
    q_m = np.roll(p_m, -1, axis=0)  # p_j
    # Distances of the previous return (p_{i-1}) and the next one (p_{j+1}) from the line through p_i and p_j.
    dev_prev = _line_deviation_m(unit, np.roll(p_m, 1, axis=0) - p_m)
    dev_next = _line_deviation_m(unit, np.roll(q_m, -1, axis=0) - q_m)
    line_prev = np.roll(adj, 1) & (dev_prev <= line_tol_m)  # pair i-1 valid: element i-1 adjacent and finite
    line_next = np.roll(adj, -1) & (dev_next <= line_tol_m)  # pair i+1 valid: element j+1 adjacent and finite
    return (line_prev & line_next) if both_sides else (line_prev | line_next)


def _chord_samples_ne_m(
    origin_ne_m: FloatArray,
    p_m: FloatArray,
    chord_m: FloatArray,
    length_m: FloatArray,
    pairs: IntArray,
    spacing_m: float,
) -> FloatArray:
    """(K, 2) north/east of the interior points of the chords ``pairs`` (``p_m`` and ``chord_m`` relative to
    ``origin_ne_m``): ``ceil(L / spacing_m) - 1`` per chord at equal steps, chord by chord."""
    counts = np.ceil(length_m[pairs] / spacing_m).astype(np.intp) - 1  # interior points per chord
    owner = np.repeat(np.arange(pairs.size), counts)
    k = np.arange(owner.size) - np.repeat(np.cumsum(counts) - counts, counts) + 1  # 1..counts per chord
    t = k / (counts[owner] + 1.0)
    idx = pairs[owner]
    return np.asarray(origin_ne_m + p_m[idx] + t[:, None] * chord_m[idx], dtype=np.float64)


def surface_fill_points(
    scan: RangeScan,
    pose: Pose,
    *,
    spacing_m: float = 0.2,
    max_gap_m: float = 1.5,
    line_tol_m: float = 0.05,
    both_sides: bool = True,
) -> FloatArray:
    """Obstacle points along the chord between adjacent sector returns that lie on one straight surface.

    The rule, why it asks for both sides and its failure modes are in the module docstring.

    Parameters
    ----------
    scan, pose:
        The scan and the pose at its measurement time (as for ``scan_to_points_ned``).
    spacing_m:
        Largest distance between neighbouring filled points [m], > 0 (the memory's merge radius fits).
    max_gap_m:
        Longest chord filled [m], > 0.
    line_tol_m:
        Largest distance of a neighbouring return from the chord's line [m], >= 0.
    both_sides:
        Require the returns on both sides on the line (the rule). False accepts one side (three returns
        on a line): measured for comparison only (``benchmarks/replay_surface_fill.py --rules``).

    Returns
    -------
    (K, 3) float64 filled points in local NED [m], at the vehicle's height, chord by chord in scan order.
    """
    _check_fill_params(spacing_m, max_gap_m, line_tol_m)
    bearings = scan_bearings_ned_rad(scan, pose)
    finite = np.isfinite(scan.ranges_m)
    adj = _adjacent_steps(bearings) & finite & np.roll(finite, -1)
    if not np.any(adj):
        return np.empty((0, 3), dtype=np.float64)
    r = np.where(finite, scan.ranges_m, 0.0)
    p = np.column_stack([r * np.cos(bearings), r * np.sin(bearings)])  # relative to the vehicle, (M, 2)
    chord = np.roll(p, -1, axis=0) - p
    length = np.hypot(chord[:, 0], chord[:, 1])
    same_surface = _same_surface(p, chord, length, adj, line_tol_m, both_sides)
    pairs = np.flatnonzero(adj & (length > spacing_m) & (length <= max_gap_m) & same_surface)
    if pairs.size == 0:
        return np.empty((0, 3), dtype=np.float64)
    samples_ne = _chord_samples_ne_m(pose.pos_ned_m[:2], p, chord, length, pairs, spacing_m)
    out = np.empty((samples_ne.shape[0], 3), dtype=np.float64)
    out[:, :2] = samples_ne
    out[:, 2] = pose.pos_ned_m[2]
    return out
