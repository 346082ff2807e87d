"""What the service reports: STATUSTEXT lines, HEARTBEAT system_status, NAMED_VALUE_FLOAT names, status JSON.

The zenoh status topic (default ``apf/status``) carries one JSON object per publication, schema
``apf.status/1``::

    {"schema": "apf.status/1", "t_s": 12.3, "state": "NAVIGATING", "reason": "...",
     "pose": {"north_m": 1.0, "east_m": 2.0, "down_m": -5.0, "yaw_deg": 45.0, "age_s": 0.04} | null,
     "goal": {"north_m": 22.0, "east_m": 22.0, "down_m": -5.0 | null, "leg": 0 | null, "legs": 1, "source": "cli",
              "held": false} | null,
     "distance_to_goal_m": 9.1 | null, "nearest_obstacle_m": 1.7 | null, "n_obstacles": 31,
     "sensor_look_deg": 0.0, "loop_latency_ms": {"p50": 0.4, "p99": 1.1, "last": 0.3} | null,
     "gc": {"collections": 12, "full": 0, "max_pause_ms": 0.3, "frozen": 55906} | null, "decision": "GREEDY" | null,
     "fence": {"outcome": "used", "note": "inclusion polygon of 6 vertices", "reads": 12, "failures": 0,
               "changes": 0, "ignored": 0, "unexpected": 0} | null,
     "autopilot": {"mode_ok": true, "armed": true, "link_alive": true}, "counters": {...},
     "rejected": {"APF_RJPOSE": 0, "APF_RJSCAN": 0, "APF_RJLINK": 0, "APF_RJSIGN": 0,
                  "APF_ERRORS": 0}}

``goal`` is the goal taken: the waypoint being flown to, or, before its first leg starts (no pose yet, waiting
for the takeover or the pilot's switch), the route's first waypoint with ``leg`` null and ``down_m`` null for "keep
the altitude"; ``held`` is true while the goal waits for a position to be checked (``goal.max_distance_m``).
``sensor_look_deg`` is where the range sensors look, learnt from the ranges: the body bearing (clockwise from the
nose) of the centre of the arc they cover, which ``[autopilot] yaw = "travel"`` points along each step; 0 without
recent readings or with all-round coverage (apf_companion/perception/coverage.py).
``gc`` is the garbage collector since the run started (apf_companion/heap.py): collections, how many were full,
the longest pause, and how many startup objects are frozen out of every collection. ``fence`` is the autopilot's
fence as read for bapf-nav's flying area (apf_companion/fencereader.py; null when the service does not read it):
the last read's outcome (used, no fence, not used, failed; null before the first read ended) and why, and the
reads, failed reads, changes, dropped answers. ``counters`` holds every
edge, perception, outbox and (``nav_`` prefixed) navigator counter; ``rejected`` the totals also sent as
NAMED_VALUE_INT (docs/hardening.md).
"""

from __future__ import annotations

import json
import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.navigator import State

__all__ = [
    "NVF_GOAL_DISTANCE",
    "NVF_NEAREST_OBSTACLE",
    "NVI_ERRORS",
    "NVI_REJECTED_LINK",
    "NVI_REJECTED_POSES",
    "NVI_REJECTED_SCANS",
    "NVI_REJECTED_SIGNING",
    "STATUS_SCHEMA",
    "encode_status_json",
    "severity_for",
    "statustext_for",
    "system_status_for",
]

STATUS_SCHEMA = "apf.status/1"
NVF_GOAL_DISTANCE = "APF_DGOAL"  # NAMED_VALUE_FLOAT names: at most 10 characters
NVF_NEAREST_OBSTACLE = "APF_DOBS"
NVI_REJECTED_POSES = "APF_RJPOSE"  # NAMED_VALUE_INT: rejected-input totals (docs/hardening.md)
NVI_REJECTED_SCANS = "APF_RJSCAN"
NVI_REJECTED_LINK = "APF_RJLINK"
NVI_REJECTED_SIGNING = "APF_RJSIGN"  # frames refused by the signing check (docs/hardening.md#mavlink-2-signing)
NVI_ERRORS = "APF_ERRORS"

_SEVERITY: dict[State, int] = {
    State.HOLDING: mavlink.MAV_SEVERITY_WARNING,
    State.STUCK: mavlink.MAV_SEVERITY_WARNING,
    State.LINK_LOST: mavlink.MAV_SEVERITY_CRITICAL,
    State.ARRIVED: mavlink.MAV_SEVERITY_NOTICE,
    State.WAITING_FOR_PILOT: mavlink.MAV_SEVERITY_NOTICE,  # the pilot has to act, nothing is wrong
}

STATUSTEXT_MAX = 50  # characters in one STATUSTEXT (no chunking needed at that length; longer: outbox chunks)


def severity_for(state: State) -> int:
    """MAV_SEVERITY of the STATUSTEXT announcing ``state``."""
    return int(_SEVERITY.get(state, mavlink.MAV_SEVERITY_INFO))


def system_status_for(state: State, *, healthy_inputs: bool) -> int:
    """HEARTBEAT.system_status: ACTIVE when in control with fresh inputs, CRITICAL when it had to hold or give
    up, STANDBY when idle (nothing to do) or waiting for the pilot to switch to GUIDED / OFFBOARD (not in control)."""
    if state in (State.HOLDING, State.STUCK, State.LINK_LOST):
        return int(mavlink.MAV_STATE_CRITICAL)
    if state in (State.NAVIGATING, State.ARRIVED):
        return int(mavlink.MAV_STATE_ACTIVE if healthy_inputs else mavlink.MAV_STATE_CRITICAL)
    return int(mavlink.MAV_STATE_STANDBY)


def statustext_for(state: State, reason: str) -> str:
    """``"APF <STATE>: <reason>"`` whole: a text longer than one STATUSTEXT (50 characters) goes in MAVLink 2
    chunks (``Outbox.statustext``, ``outbox.statustext_chunks``), so the reason's end is not lost."""
    return f"APF {state.value}: {reason}"


def _num(value: float | None, digits: int = 3) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


def encode_status_json(status: dict[str, Any]) -> bytes:
    """One status record as compact JSON (non-finite numbers become null)."""

    def clean(v: Any) -> Any:
        if isinstance(v, float):
            return _num(v, 4)
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    obj = {"schema": STATUS_SCHEMA, **clean(status)}
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
