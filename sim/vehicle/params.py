"""The simulated autopilot's parameters (PARAM_REQUEST_LIST / READ / SET), per profile.

Names, units and defaults follow each autopilot (ArduCopter: ``GUID_TIMEOUT`` s, ``WPNAV_*`` cm and cm/s;
PX4: ``COM_OF_LOSS_T`` s, ``MPC_*`` m/s); ``SIM_*`` parameters belong to the simulator (noise, sensor, vehicle).
Every value is a float on the wire (MAV_PARAM_TYPE_REAL32). A set outside [lo, hi] is refused: the reply
repeats the old value and a STATUSTEXT says why.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from apf_companion.autopilot import Autopilot
from apf_companion.errors import ConfigError

__all__ = ["SR_GROUPS", "ParamSpec", "ParamTable", "param_specs"]


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamSpec:
    name: str
    default: float
    lo: float
    hi: float
    doc: str


_SIM = (
    ParamSpec(
        name="SIM_POS_NOISE",
        default=0.0,
        lo=0.0,
        hi=5.0,
        doc="actuation noise: horizontal displacement error SD per period, per axis [m] (paper: 0.1)",
    ),
    ParamSpec(
        name="SIM_NOISE_PER",
        default=0.1,
        lo=0.01,
        hi=10.0,
        doc="actuation noise period: one N(0, SD^2) displacement per axis per period [s]",
    ),
    ParamSpec(
        name="SIM_VEH_RADIUS",
        default=0.25,
        lo=0.0,
        hi=5.0,
        doc="vehicle radius for collisions [m] (paper: 0.25 to a point obstacle)",
    ),
    ParamSpec(name="SIM_RNG_RATE", default=10.0, lo=0.0, hi=100.0, doc="range sensor rate [Hz] (0 = off)"),
    ParamSpec(name="SIM_RNG_MAX", default=8.0, lo=0.5, hi=600.0, doc="range sensor max range [m] (paper: 8)"),
    ParamSpec(name="SIM_RNG_MIN", default=0.2, lo=0.0, hi=10.0, doc="range sensor min range [m]"),
    ParamSpec(name="SIM_RNG_NOISE", default=0.0, lo=0.0, hi=10.0, doc="range noise SD [m]"),
    ParamSpec(name="SIM_RNG_DROP", default=0.0, lo=0.0, hi=1.0, doc="probability a reading is lost (unknown)"),
)

_ARDUPILOT = (
    ParamSpec(
        name="GUID_TIMEOUT",
        default=3.0,
        lo=0.1,
        hi=5.0,
        doc="GUIDED: velocity/acceleration target expires after this without an update [s]",
    ),
    ParamSpec(name="WPNAV_SPEED", default=500.0, lo=20.0, hi=2000.0, doc="max horizontal speed [cm/s]"),
    ParamSpec(name="WPNAV_ACCEL", default=250.0, lo=50.0, hi=500.0, doc="horizontal acceleration [cm/s/s]"),
    ParamSpec(name="WPNAV_SPEED_UP", default=250.0, lo=10.0, hi=1000.0, doc="climb speed [cm/s]"),
    ParamSpec(name="WPNAV_SPEED_DN", default=150.0, lo=10.0, hi=500.0, doc="descent speed [cm/s]"),
    ParamSpec(name="WPNAV_ACCEL_Z", default=100.0, lo=50.0, hi=500.0, doc="vertical acceleration [cm/s/s]"),
    ParamSpec(name="LAND_SPEED", default=50.0, lo=30.0, hi=200.0, doc="final landing speed [cm/s]"),
    ParamSpec(name="RTL_ALT", default=1500.0, lo=200.0, hi=8000.0, doc="RTL return altitude [cm]"),
    ParamSpec(
        name="DISARM_DELAY",
        default=10.0,
        lo=0.0,
        hi=127.0,
        doc="auto-disarm after this long landed and armed [s] (0 = never)",
    ),
    # AC_PosControl.cpp (Copter defaults), used by the ``arducopter`` dynamics (sim/vehicle/poscontrol.py)
    ParamSpec(name="PSC_JERK_XY", default=5.0, lo=1.0, hi=20.0, doc="horizontal jerk limit of the shaping [m/s/s/s]"),
    ParamSpec(name="PSC_JERK_Z", default=5.0, lo=5.0, hi=50.0, doc="vertical jerk limit of the shaping [m/s/s/s]"),
    ParamSpec(name="PSC_POSXY_P", default=1.0, lo=0.5, hi=2.0, doc="horizontal position P gain [1/s]"),
    ParamSpec(name="PSC_VELXY_P", default=2.0, lo=0.1, hi=6.0, doc="horizontal velocity P gain [1/s]"),
    ParamSpec(name="PSC_VELXY_I", default=1.0, lo=0.02, hi=1.0, doc="horizontal velocity I gain [1/s/s]"),
    ParamSpec(name="PSC_POSZ_P", default=1.0, lo=1.0, hi=3.0, doc="vertical position P gain [1/s]"),
    ParamSpec(name="PSC_VELZ_P", default=5.0, lo=1.0, hi=8.0, doc="vertical velocity P gain [1/s]"),
    ParamSpec(name="ANGLE_MAX", default=3000.0, lo=1000.0, hi=8000.0, doc="maximum lean angle [cdeg]"),
    ParamSpec(name="MOT_SPOOL_TIME", default=0.5, lo=0.05, hi=2.0, doc="motor spool-up time [s]"),
    ParamSpec(
        name="TKOFF_SLEW_TIME",
        default=2.0,
        lo=0.25,
        hi=5.0,
        doc="takeoff throttle slew, minimum to maximum [s]; liftoff at 90 % (mode.cpp auto_takeoff_run)",
    ),
    ParamSpec(
        name="ATC_INPUT_TC",
        default=0.15,
        lo=0.0,
        hi=1.0,
        doc="attitude input time constant [s]; arducopter dynamics: the lag of the lean (acceleration) response",
    ),
    ParamSpec(
        name="SIM_DRAG",
        default=0.4,
        lo=0.0,
        hi=2.0,
        doc="arducopter dynamics: linear horizontal drag [1/s], fitted to the SITL 5 m step (issue 8)",
    ),
    # AP_Proximity_Params.cpp: read at boot (@RebootRequired); sim/vehicle/proximity.py
    ParamSpec(
        name="PRX1_TYPE",
        default=0.0,
        lo=0.0,
        hi=20.0,
        doc="proximity sensor type, applied at boot: 0 none, 2 MAVLink (OBSTACLE_DISTANCE); others not simulated",
    ),
    ParamSpec(name="PRX1_ORIENT", default=0.0, lo=0.0, hi=1.0, doc="proximity orientation: 0 default, 1 upside down"),
    ParamSpec(name="PRX1_YAW_CORR", default=0.0, lo=-180.0, hi=180.0, doc="proximity yaw correction [deg]"),
    ParamSpec(
        name="SIM_EKF_ORIGIN_S",
        default=20.0,
        lo=0.0,
        hi=600.0,
        doc="seconds after boot until the EKF origin is set (SITL: about 20 s, issue 8); fast start = 0",
    ),
    ParamSpec(
        name="WP_YAW_BEHAVIOR",
        default=2.0,
        lo=0.0,
        hi=3.0,
        doc="yaw when a target has none: 0 keep heading, else face the direction of travel",
    ),
)

# AC_Fence.cpp (Copter defaults): stored, served and enforced (sim.vehicle.fencebreach); the service reads them
_FENCE = (
    ParamSpec(name="FENCE_ENABLE", default=0.0, lo=0.0, hi=1.0, doc="fence master switch (1 while a fence is served)"),
    ParamSpec(
        name="FENCE_TYPE",
        default=7.0,
        lo=0.0,
        hi=15.0,
        doc="fences: 1 max alt, 2 circle, 4 polygons, 8 min alt",
    ),
    ParamSpec(name="FENCE_ACTION", default=1.0, lo=0.0, hi=7.0, doc="breach action: 0 report only, 1 RTL or land"),
    ParamSpec(name="FENCE_RADIUS", default=300.0, lo=0.0, hi=10000.0, doc="circle fence radius round home [m]"),
    ParamSpec(name="FENCE_ALT_MAX", default=100.0, lo=0.0, hi=1000.0, doc="ceiling above home [m]"),
    ParamSpec(name="FENCE_ALT_MIN", default=-10.0, lo=-100.0, hi=100.0, doc="floor above home [m] (FENCE_TYPE 8)"),
    ParamSpec(name="FENCE_MARGIN", default=2.0, lo=0.0, hi=10.0, doc="distance planners keep from the fence [m]"),
    ParamSpec(name="FENCE_MARGIN_XY", default=0.0, lo=0.0, hi=50.0, doc="horizontal margin [m] (0 = FENCE_MARGIN)"),
    ParamSpec(name="FENCE_OPTIONS", default=0.0, lo=0.0, hi=7.0, doc="bit 1: union of the inclusion zones"),
)

# SRn_* stream rates [Hz] of the stream groups the simulator builds (GCS_MAVLink_Copter.cpp; default 0: nothing
# streams unasked). Read at boot (like ArduPilot, which initialises its message intervals from them at startup):
# ``--param SR0_POSITION=10`` streams LOCAL_POSITION_NED and GLOBAL_POSITION_INT on link 0 from boot.
SR_GROUPS = ("EXT_STAT", "POSITION", "EXTRA1", "EXTRA2", "EXTRA3")
SR_LINKS = 4
_STREAM_RATES = tuple(
    ParamSpec(name=f"SR{n}_{group}", default=0.0, lo=0.0, hi=50.0, doc=f"link {n}: {group} stream rate at boot [Hz]")
    for n in range(SR_LINKS)
    for group in SR_GROUPS
)

_PX4 = (
    ParamSpec(
        name="COM_OF_LOSS_T",
        default=1.0,
        lo=0.0,
        hi=60.0,
        doc="OFFBOARD: setpoint loss timeout before the failsafe [s]",
    ),
    ParamSpec(
        name="COM_OBL_RC_ACT",
        default=0.0,
        lo=0.0,
        hi=7.0,
        doc="OFFBOARD loss action: 0-2,5 Hold (no RC), 3 Return, 4 Land, 6-7 Land",
    ),
    ParamSpec(name="MPC_XY_VEL_MAX", default=12.0, lo=0.0, hi=20.0, doc="max horizontal speed [m/s]"),
    ParamSpec(
        name="MPC_XY_CRUISE", default=5.0, lo=0.5, hi=20.0, doc="horizontal speed towards a position target [m/s]"
    ),
    ParamSpec(name="MPC_ACC_HOR", default=3.0, lo=2.0, hi=15.0, doc="horizontal acceleration [m/s/s]"),
    ParamSpec(
        name="MPC_YAWRAUTO_MAX", default=45.0, lo=5.0, hi=360.0, doc="max yaw rate towards a commanded yaw [deg/s]"
    ),
    ParamSpec(name="MPC_Z_VEL_MAX_UP", default=3.0, lo=0.5, hi=8.0, doc="climb speed [m/s]"),
    ParamSpec(name="MPC_Z_VEL_MAX_DN", default=1.5, lo=0.5, hi=4.0, doc="descent speed [m/s]"),
    ParamSpec(name="MPC_TKO_SPEED", default=1.5, lo=1.0, hi=5.0, doc="takeoff climb speed [m/s]"),
    ParamSpec(name="MPC_TKO_RAMP_T", default=3.0, lo=0.0, hi=5.0, doc="takeoff speed ramp time [s]"),
    ParamSpec(name="COM_SPOOLUP_TIME", default=1.0, lo=0.0, hi=30.0, doc="motor spool-up after arming [s]"),
    ParamSpec(name="MPC_LAND_SPEED", default=0.7, lo=0.6, hi=3.0, doc="landing speed below MPC_LAND_ALT2 [m/s]"),
    ParamSpec(name="MPC_LAND_ALT1", default=10.0, lo=0.0, hi=122.0, doc="land: slowing down starts below [m]"),
    ParamSpec(name="MPC_LAND_ALT2", default=5.0, lo=0.0, hi=122.0, doc="land: MPC_LAND_SPEED below [m]"),
    ParamSpec(name="MIS_TAKEOFF_ALT", default=2.5, lo=0.0, hi=80.0, doc="default takeoff altitude [m]"),
    ParamSpec(name="RTL_RETURN_ALT", default=30.0, lo=0.0, hi=150.0, doc="RTL return altitude [m]"),
    # geofence_params.c: stored, served and enforced (sim.vehicle.fencebreach)
    ParamSpec(name="GF_ACTION", default=2.0, lo=0.0, hi=5.0, doc="geofence breach action: 0 none, 1 warn, 2 hold, ..."),
    ParamSpec(name="GF_MAX_HOR_DIST", default=0.0, lo=0.0, hi=10000.0, doc="max distance from home [m] (0 = off)"),
    ParamSpec(name="GF_MAX_VER_DIST", default=0.0, lo=0.0, hi=10000.0, doc="max height above home [m] (0 = off)"),
    ParamSpec(
        name="COM_DISARM_PRFLT",
        default=10.0,
        lo=-1.0,
        hi=20.0,
        doc="auto-disarm after this long landed and armed [s] (<= 0 = never)",
    ),
)


def param_specs(profile: Autopilot) -> tuple[ParamSpec, ...]:
    """The parameter list of a profile, in PARAM_VALUE index order."""
    return (_ARDUPILOT + _FENCE + _STREAM_RATES if profile is Autopilot.ARDUPILOT else _PX4) + _SIM


class ParamTable:
    """Current parameter values with range checks; index order is stable."""

    def __init__(self, profile: Autopilot, overrides: Mapping[str, float] | None = None) -> None:
        self.specs = param_specs(profile)
        self._by_name = {s.name: s for s in self.specs}
        self._index = {s.name: i for i, s in enumerate(self.specs)}
        self._values = {s.name: float(s.default) for s in self.specs}
        for name, value in (overrides or {}).items():
            err = self.set(name, value)
            if err is not None:
                raise ConfigError(err)

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def __len__(self) -> int:
        return len(self.specs)

    def index(self, name: str) -> int:
        return self._index[name]

    def name_at(self, index: int) -> str | None:
        return self.specs[index].name if 0 <= index < len(self.specs) else None

    def set(self, name: str, value: float) -> str | None:
        """Set a value; returns None on success, else the reason it was refused."""
        spec = self._by_name.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        if not math.isfinite(value) or not spec.lo <= value <= spec.hi:
            return f"{name} {value:g} not in [{spec.lo:g}, {spec.hi:g}]"
        self._values[name] = float(value)
        return None

    def items(self) -> list[tuple[str, float]]:
        return [(s.name, self._values[s.name]) for s in self.specs]
