"""Value types of the perception layer: poses, range scans, goal commands.

Frames and angles (see docs/perception.md for the diagram):

- Positions are local NED (x north, y east, z down) in metres, relative to the autopilot's EKF origin.
- Body-frame bearings are FRD: 0 = forward, clockwise positive seen from above (towards the right side).
- North-aligned bearings (``ScanFrame.LOCAL_NED``) are 0 = north, clockwise positive (towards east).
- Ranges: NaN = no usable reading (unknown or invalid; ``SectorCounts`` tells which), +inf = free out to
  ``range_max_m``, finite = an obstacle at that distance.

All times ``t_s`` are seconds on the service's monotonic clock (the caller maps autopilot ``time_boot_ms``
or receive time onto it); a scan and the pose used to place it must share that clock.

The array fields are copied to read-only float64 arrays, so the frozen records really are immutable.
Equality compares array contents (NaN equal to NaN); the records are not hashable.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError

__all__ = [
    "FloatArray",
    "GoalCommand",
    "Pose",
    "RangeScan",
    "ScanFrame",
    "SectorCounts",
]

FloatArray = npt.NDArray[np.float64]


def _frozen_array(value: Any, *, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """Copy ``value`` to a read-only float64 array and check its shape (None = any length)."""
    try:
        arr = np.array(value, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as err:
        msg = f"{name} must be a float array of shape {shape}, got {value!r}"
        raise ConfigError(msg) from err
    if arr.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(arr.shape, shape, strict=True)
    ):
        msg = f"{name} must have shape {shape}, got {arr.shape}"
        raise ConfigError(msg)
    arr.setflags(write=False)
    return arr


class ScanFrame(enum.Enum):
    """The reference direction of a scan's bearings (both clockwise positive seen from above)."""

    BODY_FRD = "body_frd"
    """0 = vehicle forward; rotated by the vehicle yaw at measurement time to reach NED."""
    LOCAL_NED = "local_ned"
    """0 = north; independent of the vehicle yaw."""


# eq=False: the hand-written __eq__ compares array contents; the record stays unhashable.
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Pose:
    """Vehicle pose at time ``t_s``.

    Attributes:
        t_s: Monotonic time of the pose [s].
        pos_ned_m: (3,) float64 position in local NED [m].
        yaw_rad: Heading, 0 = north, clockwise positive (towards east) [rad].
        vel_ned_m_s: (3,) velocity in local NED as the autopilot reports it (LOCAL_POSITION_NED vx/vy/vz), or
            None when not reported or not plausible [m/s].
    """

    t_s: float
    pos_ned_m: FloatArray
    yaw_rad: float
    vel_ned_m_s: FloatArray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "pos_ned_m", _frozen_array(self.pos_ned_m, name="pos_ned_m", shape=(3,)))
        if not math.isfinite(self.t_s):
            msg = f"t_s must be finite, got {self.t_s}"
            raise ConfigError(msg)
        if not math.isfinite(self.yaw_rad):
            msg = f"yaw_rad must be finite, got {self.yaw_rad}"
            raise ConfigError(msg)
        if not np.all(np.isfinite(self.pos_ned_m)):
            msg = f"pos_ned_m must be finite, got {self.pos_ned_m}"
            raise ConfigError(msg)
        if self.vel_ned_m_s is not None:
            object.__setattr__(self, "vel_ned_m_s", _frozen_array(self.vel_ned_m_s, name="vel_ned_m_s", shape=(3,)))
            if not np.all(np.isfinite(self.vel_ned_m_s)):
                msg = f"vel_ned_m_s must be finite, got {self.vel_ned_m_s}"
                raise ConfigError(msg)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return (
            self.t_s == other.t_s
            and self.yaw_rad == other.yaw_rad
            and bool(np.array_equal(self.pos_ned_m, other.pos_ned_m))
            and (
                self.vel_ned_m_s is other.vel_ned_m_s
                or (
                    self.vel_ned_m_s is not None
                    and other.vel_ned_m_s is not None
                    and bool(np.array_equal(self.vel_ned_m_s, other.vel_ned_m_s))
                )
            )
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, slots=True, kw_only=True)
class SectorCounts:
    """How the elements of one scan were classified.

    Attributes:
        valid: Finite ranges inside [range_min_m, range_max_m] (obstacles).
        free: Readings meaning "nothing up to range_max_m" (stored as +inf).
        unknown: Readings the sensor marks as unknown or unused (stored as NaN).
        invalid: Readings rejected as implausible, e.g. below range_min_m (stored as NaN).
    """

    valid: int = 0
    free: int = 0
    unknown: int = 0
    invalid: int = 0

    def __post_init__(self) -> None:
        for name in ("valid", "free", "unknown", "invalid"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                msg = f"SectorCounts.{name} must be an int >= 0, got {value!r}"
                raise ConfigError(msg)

    @property
    def total(self) -> int:
        """Number of elements in the scan."""
        return self.valid + self.free + self.unknown + self.invalid


# eq=False: the hand-written __eq__ compares array contents; the record stays unhashable.
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class RangeScan:
    """A planar set of range readings at known bearings, taken at one time.

    Attributes:
        t_s: Monotonic time of the measurement [s]; pick the pose at this time to place the points.
        frame: Reference of ``bearings_rad``: ``BODY_FRD`` (0 = forward) or ``LOCAL_NED`` (0 = north);
            clockwise positive in both.
        bearings_rad: (M,) float64 bearings [rad].
        ranges_m: (M,) float64 ranges [m]: finite = obstacle, +inf = free, NaN = unknown or invalid.
        range_min_m: Smallest range the sensor reports [m].
        range_max_m: Largest range the sensor reports [m].
        time_boot_ms: Sensor timestamp from the source message, if it had one [ms].
        counts: Classification of the M elements; when omitted it is derived from ``ranges_m``
            (every NaN counted as unknown).
        source: Free-form origin label for logs (e.g. ``"mavlink:obstacle_distance"``).
    """

    t_s: float
    frame: ScanFrame
    bearings_rad: FloatArray
    ranges_m: FloatArray
    range_min_m: float
    range_max_m: float
    time_boot_ms: int | None = None
    counts: SectorCounts = field(default_factory=SectorCounts)
    source: str = ""

    def __post_init__(self) -> None:
        bearings = _frozen_array(self.bearings_rad, name="bearings_rad", shape=(None,))
        ranges = _frozen_array(self.ranges_m, name="ranges_m", shape=(None,))
        object.__setattr__(self, "bearings_rad", bearings)
        object.__setattr__(self, "ranges_m", ranges)
        if bearings.shape != ranges.shape:
            msg = f"bearings_rad and ranges_m differ in length: {bearings.size} and {ranges.size}"
            raise ConfigError(msg)
        if not isinstance(self.frame, ScanFrame):
            msg = f"frame must be a ScanFrame, got {self.frame!r}"
            raise ConfigError(msg)
        if not math.isfinite(self.t_s):
            msg = f"t_s must be finite, got {self.t_s}"
            raise ConfigError(msg)
        if not np.all(np.isfinite(bearings)):
            msg = "bearings_rad must be finite"
            raise ConfigError(msg)
        if not (
            math.isfinite(self.range_min_m)
            and math.isfinite(self.range_max_m)
            and 0.0 <= self.range_min_m <= self.range_max_m
        ):
            msg = (
                "range_min_m and range_max_m must be finite with 0 <= range_min_m <= range_max_m, "
                f"got {self.range_min_m} and {self.range_max_m}"
            )
            raise ConfigError(msg)
        if np.any(ranges < 0.0) or np.any(np.isneginf(ranges)):
            msg = "ranges_m must be >= 0, +inf (free) or NaN (no reading)"
            raise ConfigError(msg)
        if self.time_boot_ms is not None and (not isinstance(self.time_boot_ms, int) or self.time_boot_ms < 0):
            msg = f"time_boot_ms must be an int >= 0 or None, got {self.time_boot_ms!r}"
            raise ConfigError(msg)
        if self.counts.total == 0 and ranges.size > 0:
            nan = int(np.count_nonzero(np.isnan(ranges)))
            inf = int(np.count_nonzero(np.isposinf(ranges)))
            object.__setattr__(self, "counts", SectorCounts(valid=ranges.size - nan - inf, free=inf, unknown=nan))
        elif self.counts.total != ranges.size:
            msg = f"counts total {self.counts.total} does not match the {ranges.size} ranges"
            raise ConfigError(msg)

    @property
    def obstacle_mask(self) -> npt.NDArray[np.bool_]:
        """(M,) True where the element is an obstacle (finite range)."""
        return np.isfinite(self.ranges_m)

    def __len__(self) -> int:
        return int(self.ranges_m.size)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RangeScan):
            return NotImplemented
        return (
            self.t_s == other.t_s
            and self.frame is other.frame
            and self.range_min_m == other.range_min_m
            and self.range_max_m == other.range_max_m
            and self.time_boot_ms == other.time_boot_ms
            and self.counts == other.counts
            and self.source == other.source
            and bool(np.array_equal(self.bearings_rad, other.bearings_rad))
            and bool(np.array_equal(self.ranges_m, other.ranges_m, equal_nan=True))
        )

    __hash__ = None  # type: ignore[assignment]


# eq=False: the hand-written __eq__ compares array contents; the record stays unhashable.
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class GoalCommand:
    """A goal position for the planner, e.g. from the zenoh command topic.

    Attributes:
        pos_ned_m: (3,) float64 goal in local NED [m].
        frame: Always ``"local_ned"`` (the only frame accepted today).
    """

    pos_ned_m: FloatArray
    frame: str = "local_ned"

    def __post_init__(self) -> None:
        object.__setattr__(self, "pos_ned_m", _frozen_array(self.pos_ned_m, name="pos_ned_m", shape=(3,)))
        if not np.all(np.isfinite(self.pos_ned_m)):
            msg = f"pos_ned_m must be finite, got {self.pos_ned_m}"
            raise ConfigError(msg)
        if self.frame != "local_ned":
            msg = f"frame must be 'local_ned', got {self.frame!r}"
            raise ConfigError(msg)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GoalCommand):
            return NotImplemented
        return self.frame == other.frame and bool(np.array_equal(self.pos_ned_m, other.pos_ned_m))

    __hash__ = None  # type: ignore[assignment]
