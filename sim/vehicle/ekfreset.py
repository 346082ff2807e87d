"""An estimator position reset on the PX4 profile: the local frame jumps, the vehicle does not.

PX4's EKF2 resets its horizontal position (GPS glitch recovery, a switch of aiding source) in one update: the
local position jumps by ``delta_xy`` and ``xy_reset_counter`` counts it (src/modules/ekf2/EKF2.cpp
``PublishLocalPosition``: ``_ekf.get_posNE_reset(&lpos.delta_xy[0], &lpos.xy_reset_counter)``). MAVLink carries
neither in LOCAL_POSITION_NED (streams/LOCAL_POSITION_NED.hpp sends x, y, z, vx, vy, vz only); ODOMETRY carries
the sum of the estimator's reset counters (EKF2.cpp ``PublishOdometry``: quat + velNE + velD + posNE + posD,
streams/ODOMETRY.hpp ``msg.reset_counter``). Position setpoints are read in the frame of the estimate: PX4 shifts
only a setpoint older than the reset by ``delta_xy`` (mc_pos_control ``adjustSetpointForEKFResets``); one sent
after it in the old frame is flown as sent.

Modelled here: the reported local position (LOCAL_POSITION_NED, ODOMETRY, GLOBAL_POSITION_INT, the
POSITION_TARGET_LOCAL_NED echo) is the truth plus ``offset_ned_m``; a local setpoint is flown at its position minus
the offset (the held target, kept as the truth, is the setpoint PX4 shifted). Not modelled: a velocity or height
reset, yaw resets, the estimator's own innovation that causes the reset.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

__all__ = ["EstimatorFrame"]

FloatArray = npt.NDArray[np.float64]


@dataclass(slots=True)
class EstimatorFrame:
    """Where the estimate's local NED frame is against the truth's, and the resets so far."""

    offset_ned_m: FloatArray = field(default_factory=lambda: np.zeros(3))  # estimate - truth [m, local NED]
    reset_counter: int = 0  # ODOMETRY.reset_counter (uint8 on the wire)

    def reset_position(self, delta_ne_m: tuple[float, float]) -> None:
        """A horizontal position reset of ``delta_ne_m`` (north, east) [m]: the estimate jumps, the vehicle not."""
        self.offset_ned_m = self.offset_ned_m + np.array([delta_ne_m[0], delta_ne_m[1], 0.0])
        self.reset_counter = (self.reset_counter + 1) % 256

    def reported(self, truth_ned_m: FloatArray) -> FloatArray:
        """A true position as the estimator reports it [m, local NED]."""
        return np.asarray(truth_ned_m + self.offset_ned_m, dtype=np.float64)

    def flown(self, setpoint_ned_m: FloatArray) -> FloatArray:
        """Where a local-frame setpoint position is in the truth [m, local NED]."""
        return np.asarray(setpoint_ned_m - self.offset_ned_m, dtype=np.float64)
