"""The global reference: the autopilot's GLOBAL_POSITION_INT paired with the local position at its own time. It
places global goals (DO_REPOSITION, the autopilot's global target) and the PX4 takeoff altitude."""

from __future__ import annotations

import math

from apf_companion.goal import GlobalReference, Route, local_goal_from_reposition
from apf_companion.links.messages import GlobalPositionInt
from apf_companion.navigator import Navigator
from apf_companion.perception import PerceptionFrontEnd

__all__ = ["GlobalPlacement"]

DEG_E7 = 1e-7
MM = 1e-3


class GlobalPlacement:
    """Owns the global reference (``global_ref``) and the GLOBAL_POSITION_INT waiting for the pose of its time."""

    def __init__(self, *, perception: PerceptionFrontEnd, navigator: Navigator) -> None:
        self._perception = perception
        self._navigator = navigator
        self.global_ref: GlobalReference | None = None
        #: A GLOBAL_POSITION_INT waiting for the pose of its time: (time_boot_ms, lat, lon [deg], alt, rel [m]).
        self._pending: tuple[int, float, float, float, float] | None = None

    def on_global_position(self, rec: GlobalPositionInt, now_s: float) -> None:
        if self._navigator.pose is None:
            return
        lat, lon = rec.lat * DEG_E7, rec.lon * DEG_E7
        alt, rel = rec.alt * MM, rec.relative_alt * MM
        if not all(math.isfinite(v) for v in (lat, lon, alt, rel)) or (rec.lat == 0 and rec.lon == 0):
            return
        self._pending = (rec.time_boot_ms, lat, lon, alt, rel)
        self.place(now_s)

    def place(self, now_s: float) -> None:
        """The global reference from the latest GLOBAL_POSITION_INT and the local position at its own time (the
        pose history, by the autopilot's boot time), not the latest pose: a vehicle at 5 m/s moves 0.5 m in the
        100 ms between the two streams, and every global goal and fence vertex placed with this pair would move
        with it. When the pose of its time has not arrived yet (the two streams of one instant in either order),
        it waits for that pose (called again after each LOCAL_POSITION_NED)."""
        if self._pending is None:
            return
        boot_ms, lat, lon, alt, rel = self._pending
        perception = self._perception
        latest = perception.history.latest()
        t = perception.scan_time(boot_ms, now_s)
        if latest is not None and t <= latest.t_s:
            p = (perception.history.at(t) or latest).pos_ned_m
        else:  # not in the history (yet, or at all: no heading for the poses); the navigator's pose once it is as new
            pose = self._navigator.pose
            if pose is None or pose.t_s < t:
                return
            p = pose.pos_ned_m
        self.global_ref = GlobalReference(
            lat_deg=lat, lon_deg=lon, alt_amsl_m=alt, alt_rel_m=rel, pos_ned_m=(float(p[0]), float(p[1]), float(p[2]))
        )
        self._pending = None

    def goal(self, *, frame: int, x: int, y: int, z: float, source: str) -> Route:
        """A DO_REPOSITION position (frame, x, y, z) as a local route, placed about the global reference where the
        frame is global (``goal.local_goal_from_reposition``: its RepositionError when it cannot be placed)."""
        return local_goal_from_reposition(frame=frame, x=x, y=y, z=z, reference=self.global_ref, source=source)

    def home_amsl_m(self) -> float | None:
        """Home altitude AMSL (GLOBAL_POSITION_INT alt - relative_alt) [m], None until heard."""
        ref = self.global_ref
        return None if ref is None else ref.alt_amsl_m - ref.alt_rel_m
