"""The autopilot's poses and the range messages to the perception front end; its new poses to the navigator.

While the service forwards its obstacles (OBSTACLE_DISTANCE), the autopilot's DISTANCE_SENSOR with ids 10-18 is
its proximity library reporting those same sectors back (``GCS_Common.cpp`` ``send_proximity``:
``PROXIMITY_SENSOR_ID_START + i``); reading it would keep every forwarded obstacle alive forever, so it is
counted (``proximity_echoes_ignored``) and dropped. PX4 echoes the same way in OBSTACLE_DISTANCE: its stream
(``src/modules/mavlink/streams/OBSTACLE_DISTANCE.hpp``) sends ``obstacle_distance_fused``, the collision-prevention
map that ``CollisionPrevention::_updateObstacleMap`` builds from its distance sensors *and* every OBSTACLE_DISTANCE
received (ours included) and publishes in MAV_FRAME_BODY_FRD; so on PX4, while forwarding, the autopilot's own
OBSTACLE_DISTANCE is counted the same way and dropped.
"""

from __future__ import annotations

from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from apf_companion.handling.globalref import GlobalPlacement
from apf_companion.handling.params import HandlerParams
from apf_companion.links.messages import (
    Attitude,
    DistanceSensor,
    LocalPositionNed,
    ObstacleDistance,
    ObstacleDistance3d,
    Odometry,
)
from apf_companion.navigator import Navigator
from apf_companion.perception import PerceptionFrontEnd, euler_yaw_rate_rad_s
from apf_companion.reporter import ServiceCounters

__all__ = ["POSE_CONFLICT_TEXT", "PROXIMITY_ECHO_IDS", "PoseRouting", "RangeRouting"]

#: STATUSTEXT when two pose streams with the autopilot's ids disagree (``PoseGate`` CONFLICT): the service brakes.
POSE_CONFLICT_TEXT = "APF BRAKING: two position streams disagree"
# AP_Proximity.h PROXIMITY_SENSOR_ID_START (10): DISTANCE_SENSOR ids of the proximity sectors (8) and upward (+9)
PROXIMITY_ECHO_IDS = range(10, 10 + 9)


class PoseRouting:
    """LOCAL_POSITION_NED, ATTITUDE and ODOMETRY to the perception front end; owns nothing.

    Args:
        global_ref: Placed again after each pose (a GLOBAL_POSITION_INT may wait for the pose of its time).
        on_pose: Called with the autopilot's ``time_boot_ms`` when the navigator accepted a new pose (it triggers
            a cycle, and the stream's gaps measure the link's loss).
        statustext: Sends a STATUSTEXT (severity, text).
    """

    def __init__(
        self,
        *,
        perception: PerceptionFrontEnd,
        navigator: Navigator,
        global_ref: GlobalPlacement,
        on_pose: Callable[[int], None],
        statustext: Callable[[int, str], None],
    ) -> None:
        self._perception = perception
        self._navigator = navigator
        self._global_ref = global_ref
        self._on_pose = on_pose
        self._statustext = statustext

    def on_local_position(self, rec: LocalPositionNed, now_s: float) -> None:
        perception, nav = self._perception, self._navigator
        pose = perception.on_local_position(
            rec.time_boot_ms, (rec.x, rec.y, rec.z), now_s, vel_ned_m_s=(rec.vx, rec.vy, rec.vz)
        )
        reset = perception.take_reset()
        if reset is not None:
            nav.recovery.position_reset(now_s, reset)
        if perception.take_conflict():  # braking with no state change: say why (the log has the details)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, POSE_CONFLICT_TEXT)
        nav.recovery.pose_confirmed = perception.gate.confirmed
        if pose is not None and nav.update_pose(pose):
            self._on_pose(rec.time_boot_ms)
        self._global_ref.place(now_s)

    def on_odometry(self, rec: Odometry, now_s: float) -> None:
        self._perception.poses.on_reset_counter(rec.reset_counter)  # estimator reset evidence for the pose gate

    def on_attitude(self, rec: Attitude, now_s: float) -> None:
        rate = euler_yaw_rate_rad_s(rec.roll, rec.pitch, rec.pitchspeed, rec.yawspeed)
        self._perception.on_attitude(rec.yaw, time_boot_ms=rec.time_boot_ms, yaw_rate_rad_s=rate)


class RangeRouting:
    """OBSTACLE_DISTANCE, DISTANCE_SENSOR and OBSTACLE_DISTANCE_3D to the perception front end (when ``[sensors]
    mavlink``), the proximity echo dropped (see the module docstring); owns nothing."""

    def __init__(self, params: HandlerParams, *, perception: PerceptionFrontEnd, counters: ServiceCounters) -> None:
        self.params = params
        self._perception = perception
        self._counters = counters

    def on_obstacle_distance(self, rec: ObstacleDistance, now_s: float) -> None:
        p = self.params
        if p.forwarding and p.profile is Autopilot.PX4 and rec.src == p.autopilot:
            self._counters.proximity_echoes_ignored += 1  # PX4's fused map: our forwarded obstacles come back
            return
        if p.mavlink_ranges:
            self._perception.on_obstacle_distance(rec, now_s)

    def on_distance_sensor(self, rec: DistanceSensor, now_s: float) -> None:
        p = self.params
        if p.forwarding and rec.src == p.autopilot and rec.sensor_id in PROXIMITY_ECHO_IDS:
            self._counters.proximity_echoes_ignored += 1
            return
        if p.mavlink_ranges:
            self._perception.on_distance_sensor(rec, now_s)

    def on_obstacle_distance_3d(self, rec: ObstacleDistance3d, now_s: float) -> None:
        if self.params.mavlink_ranges:
            self._perception.on_obstacle_distance_3d(rec, now_s)
