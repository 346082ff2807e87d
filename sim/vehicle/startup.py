"""The estimator's start: no position until the EKF has an origin (ArduCopter SITL: about 20 s after boot).

Before the origin is set a real ArduCopter sends no LOCAL_POSITION_NED (``GCS_Common.cpp`` send_local_position
returns without an origin) and no HOME_POSITION (send_home_position: home not set); GLOBAL_POSITION_INT still goes
out with the stale, zero location (send_global_position_int ignores ``get_location``'s result); modes that need a
position refuse to start (``mode.cpp`` set_mode: "requires position") and arming in them fails
("PreArm: Need Position Estimate", ``AP_Arming_Copter.cpp`` mandatory_position_checks); EKF_STATUS_REPORT has no
horizontal position flags. When the origin is set the EKF says "EKF3 IMU0 origin set" (``NavEKF3_core.cpp``
setOrigin) and everything above becomes available.

The delay is the profile's (``AutopilotProfile.ekf_origin_delay_s``: ArduCopter ``SIM_EKF_ORIGIN_S``, 20 s; PX4 0);
``EngineConfig.fast_start`` and an airborne spawn (a flying vehicle has an origin) skip it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["EKF_FLAGS_NO_ORIGIN", "EKF_FLAGS_ORIGIN", "ORIGIN_TEXT", "EkfStartup"]

ORIGIN_TEXT = "EKF3 IMU0 origin set"  # NavEKF3_core.cpp setOrigin, MAV_SEVERITY_INFO
# EKF_STATUS_REPORT.flags (NavEKF3_Outputs.cpp send_status_report, from the filter status): attitude, velocities
# and height from the start, in constant-position mode without GPS; the horizontal position once the origin is set.
EKF_FLAGS_NO_ORIGIN = int(
    mavlink.EKF_ATTITUDE
    | mavlink.EKF_VELOCITY_HORIZ
    | mavlink.EKF_VELOCITY_VERT
    | mavlink.EKF_POS_VERT_ABS
    | mavlink.EKF_CONST_POS_MODE
)
EKF_FLAGS_ORIGIN = int(
    mavlink.EKF_ATTITUDE
    | mavlink.EKF_VELOCITY_HORIZ
    | mavlink.EKF_VELOCITY_VERT
    | mavlink.EKF_POS_HORIZ_REL
    | mavlink.EKF_POS_HORIZ_ABS
    | mavlink.EKF_POS_VERT_ABS
    | mavlink.EKF_PRED_POS_HORIZ_REL
    | mavlink.EKF_PRED_POS_HORIZ_ABS
)


class EkfStartup:
    """Whether the EKF origin is set yet; ``tick`` sets it once the profile's delay has passed."""

    def __init__(self, *, skip: bool, boot_t_s: float = 0.0) -> None:
        self.origin_set = skip
        self.origin_t_s: float | None = boot_t_s if skip else None
        self.boot_t_s = boot_t_s  # the delay counts from the (re)boot

    def tick(self, v: VehicleEngine) -> None:
        if self.origin_set or v.t_s - self.boot_t_s < v.profile_rules.ekf_origin_delay_s(v.params) - 1e-9:
            return
        self.origin_set = True
        self.origin_t_s = v.t_s
        v.statustext(mavlink.MAV_SEVERITY_INFO, ORIGIN_TEXT)

    @property
    def flags(self) -> int:
        return EKF_FLAGS_ORIGIN if self.origin_set else EKF_FLAGS_NO_ORIGIN
