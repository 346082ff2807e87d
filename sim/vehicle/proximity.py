"""ArduPilot's proximity library with a MAVLink backend (PRX1_TYPE = 2), as the ArduPilot profile models it.

What the real one does, and this copies:

- ``AP_Proximity::init`` creates the backends from PRX1_TYPE once, at boot (``@RebootRequired``): a PRX1_TYPE set
  over PARAM_SET takes effect after MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN. 0 = none; 2 = MAVLink; any other type is a
  serial/CAN device that is not simulated, so it never connects.
- ``AP_Proximity_MAV::handle_obstacle_distance_msg``: the message's ``frame`` is ignored, element ``j`` lies at
  the body bearing ``j * increment + angle_offset + PRX1_YAW_CORR`` (``increment`` negated with PRX1_ORIENT = 1),
  ``increment_f`` wins over ``increment`` and both 0 drops the message; readings of 0, UINT16_MAX or outside
  ``[min_distance, max_distance]`` are skipped; each message replaces the whole boundary (``boundary.reset()``),
  and each of the 8 faces of 45 deg (``AP_Proximity_Boundary_3D::get_face``: ``(yaw + 22.5) / 45``) keeps its
  nearest reading.
- ``AP_Proximity_MAV::update``: status Good while the last message is at most ``PROXIMITY_MAV_TIMEOUT_MS``
  (500 ms) old, NoData after (and before the first).
- SYS_STATUS (``ArduCopter/GCS_Copter.cpp`` ``update_vehicle_sensor_status_flags``): PROXIMITY present when the
  status is not NotConnected, enabled when PRX1_TYPE is not 0, healthy when the status is Good.
- DISTANCE_SENSOR (``GCS_Common.cpp`` ``send_proximity``, stream EXTRA3): only while Good, one message per face
  that is valid or has been valid before (``proximity_ever_valid_bitmask``), id ``10 + face``
  (``PROXIMITY_SENSOR_ID_START``), orientation = face (MAV_SENSOR_ROTATION_YAW_0 + 45 deg steps), the backend's
  min/max distance, an invalid face at max_distance. ArduPilot keeps the ever-valid mask per link; here it is one.

Not modelled: DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D into the proximity library, PRX1_IGN_*, PRX1_MIN/MAX, the
object-avoidance database and simple avoidance.
"""

from __future__ import annotations

import enum
import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.perception import obstacle_distance_element_count
from sim.vehicle.params import ParamTable

__all__ = ["PROXIMITY_TIMEOUT_S", "Proximity", "ProximityStatus"]

PROXIMITY_TIMEOUT_S = 0.5  # AP_Proximity_MAV.cpp PROXIMITY_MAV_TIMEOUT_MS
PRX_TYPE_NONE = 0
PRX_TYPE_MAVLINK = 2
FACES = 8  # PROXIMITY_MAX_DIRECTION: horizontal faces of 45 deg
FACE_DEG = 45.0
SENSOR_ID_START = 10  # AP_Proximity.h PROXIMITY_SENSOR_ID_START
UINT16_MAX = 65535
SENSOR_BIT = int(mavlink.MAV_SYS_STATUS_SENSOR_PROXIMITY)


class ProximityStatus(enum.Enum):
    """AP_Proximity::Status."""

    NOT_CONNECTED = "not_connected"
    NO_DATA = "no_data"
    GOOD = "good"


class Proximity:
    """The proximity library of one boot: the PRX1_* values read at boot, the 8 faces, the last update time."""

    def __init__(self, prx_type: float, orient: float, yaw_corr_deg: float) -> None:
        self.prx_type = round(prx_type)
        self.orient = round(orient)
        self.yaw_corr_deg = max(-360.0, min(360.0, yaw_corr_deg))
        self.faces_m: list[float | None] = [None] * FACES
        self.min_m = 0.0
        self.max_m = 0.0
        self.last_update_s: float | None = None
        self.ever_valid = [False] * FACES
        self.messages = 0  # OBSTACLE_DISTANCE taken

    @classmethod
    def at_boot(cls, params: ParamTable) -> Proximity:
        """The library as PRX1_* stand at boot (none on a profile without PRX1_TYPE: PX4)."""
        if "PRX1_TYPE" not in params:
            return cls(PRX_TYPE_NONE, 0.0, 0.0)
        return cls(params["PRX1_TYPE"], params["PRX1_ORIENT"], params["PRX1_YAW_CORR"])

    @property
    def mavlink_backend(self) -> bool:
        return self.prx_type == PRX_TYPE_MAVLINK

    def status(self, t_s: float) -> ProximityStatus:
        if not self.mavlink_backend:
            return ProximityStatus.NOT_CONNECTED
        last = self.last_update_s
        if last is None or t_s - last > PROXIMITY_TIMEOUT_S:
            return ProximityStatus.NO_DATA
        return ProximityStatus.GOOD

    def sensor_flags(self, t_s: float) -> tuple[int, int, int]:
        """SYS_STATUS (present, enabled, health) bits of MAV_SYS_STATUS_SENSOR_PROXIMITY."""
        status = self.status(t_s)
        present = SENSOR_BIT if status is not ProximityStatus.NOT_CONNECTED else 0
        enabled = SENSOR_BIT if self.prx_type != PRX_TYPE_NONE else 0
        health = SENSOR_BIT if status is ProximityStatus.GOOD else 0
        return present, enabled, health

    def on_obstacle_distance(self, msg: Any, t_s: float) -> None:
        """An OBSTACLE_DISTANCE from anyone (it has no target) while the MAVLink backend exists."""
        if not self.mavlink_backend:
            return
        increment = float(msg.increment_f) if msg.increment_f != 0 else float(msg.increment)
        if increment == 0 or not math.isfinite(increment):
            return  # "invalid increment"
        n = obstacle_distance_element_count(increment)  # ArduPilot's rule, halves up (AP_Proximity_MAV.cpp)
        min_cm, max_cm = int(msg.min_distance), int(msg.max_distance)
        self.min_m, self.max_m = min_cm * 0.01, max_cm * 0.01
        self.last_update_s = t_s
        self.messages += 1
        yaw_corr = (self.yaw_corr_deg + float(msg.angle_offset)) % 360.0
        if self.orient != 0:
            increment = -increment
        faces: list[float | None] = [None] * FACES
        for j, d_cm in enumerate(msg.distances[:n]):
            if d_cm == 0 or d_cm == UINT16_MAX or d_cm < min_cm or d_cm > max_cm:
                continue
            face = int(((j * increment + yaw_corr) % 360.0 + FACE_DEG / 2.0) % 360.0 // FACE_DEG)
            d_m = d_cm * 0.01
            old = faces[face]
            faces[face] = d_m if old is None else min(old, d_m)
        self.faces_m = faces  # the whole boundary is replaced by each message

    def distance_sensor_msgs(self, mav: Any, t_s: float, time_boot_ms: int) -> list[Any]:
        """The DISTANCE_SENSOR messages ``send_proximity`` sends now (none unless Good)."""
        if self.status(t_s) is not ProximityStatus.GOOD:
            return []
        min_cm, max_cm = int(self.min_m * 100.0), int(self.max_m * 100.0)
        out = []
        for face, d_m in enumerate(self.faces_m):
            if d_m is not None:
                self.ever_valid[face] = True
            elif not self.ever_valid[face]:
                continue  # never valid: not sent
            d_cm = int((d_m if d_m is not None else self.max_m) * 100.0)
            kind, orientation = mavlink.MAV_DISTANCE_SENSOR_LASER, mavlink.MAV_SENSOR_ROTATION_NONE + face
            msg = mav.distance_sensor_encode(
                time_boot_ms, min_cm, max_cm, d_cm, kind, SENSOR_ID_START + face, orientation, 0
            )
            out.append(msg)
        return out
