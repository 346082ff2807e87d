"""Adopting the autopilot's guided target as the goal (``[goal] adopt_autopilot_target``).

A ground station's "Fly here" (Mission Planner), "Go to location" (QGroundControl) or ``guided`` (MAVProxy) goes
to the autopilot, not to the companion. The autopilot reports the guided target it now holds in
POSITION_TARGET_LOCAL_NED or POSITION_TARGET_GLOBAL_INT (ArduCopter ``GCS_MAVLink_Copter.cpp``
send_position_target_*: GLOBAL_INT for a guided WP destination, LOCAL_NED for position/velocity targets). In
this mode the service takes such a target as its goal and flies there around obstacles, overriding the target
with its own setpoints.

Those reports echo the service's own setpoints too, so a target is new only when it is farther than
``tolerance_m`` from every setpoint the service sent in the last ``ECHO_WINDOW_S`` (the autopilot reports with a
lag, and ArduCopter moves a position+velocity target along its velocity), from the last setpoint it sent at all
(the autopilot holds it after the service goes quiet), from the current goal, and from the vehicle itself (a
mode change makes the autopilot hold where it is). Targets that ignore the position (velocity-only) are not
goals. Only in GUIDED / OFFBOARD: in other modes the report is not a command.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from apf_companion.autopilot import TypeMask

__all__ = ["ECHO_WINDOW_S", "AdoptParams", "SentSetpoints", "is_new_target"]

ECHO_WINDOW_S = 3.0  # [s] the autopilot's report may lag what was sent by this much (ArduCopter GUID_TIMEOUT: 3 s)
SENT_KEPT = 512  # bound on remembered setpoints (the window at 50 Hz is 150)
_HORIZONTAL_IGNORE = TypeMask.X_IGNORE | TypeMask.Y_IGNORE

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True, kw_only=True)
class AdoptParams:
    enabled: bool = False  # [goal] adopt_autopilot_target
    tolerance_m: float = 1.0  # [goal] adopt_tolerance_m


class SentSetpoints:
    """The positions of setpoints sent lately (service time), and the last one whatever its age."""

    def __init__(self) -> None:
        self._recent: collections.deque[tuple[float, Vec3]] = collections.deque(maxlen=SENT_KEPT)

    def add(self, t_s: float, pos_ned_m: Vec3) -> None:
        self._recent.append((t_s, pos_ned_m))

    def since(self, t_s: float) -> list[Vec3]:
        """Positions sent at or after ``t_s``, plus the newest one."""
        out = [p for t, p in self._recent if t >= t_s]
        if self._recent and not out:
            out.append(self._recent[-1][1])
        return out


def _dist(a: Sequence[float], b: Sequence[float]) -> float:
    """3-D distance; a NaN down (keep the altitude) compares horizontally."""
    dz = a[2] - b[2]
    return math.hypot(a[0] - b[0], a[1] - b[1], 0.0 if math.isnan(dz) else dz)


def is_new_target(
    target_ned_m: Vec3,
    type_mask: int,
    *,
    sent: Iterable[Vec3],
    goal_ned_m: Sequence[float] | None,
    pose_ned_m: Sequence[float] | None,
    tolerance_m: float,
) -> bool:
    """Whether a reported guided target is a goal someone else gave (see the module docstring)."""
    if type_mask & _HORIZONTAL_IGNORE or not all(math.isfinite(v) for v in target_ned_m):
        return False
    if pose_ned_m is None or _dist(target_ned_m, pose_ned_m) <= tolerance_m:
        return False
    if goal_ned_m is not None and _dist(target_ned_m, goal_ned_m) <= tolerance_m:
        return False
    return all(_dist(target_ned_m, p) > tolerance_m for p in sent)
