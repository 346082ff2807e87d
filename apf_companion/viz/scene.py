"""One cycle's snapshot as Foxglove messages (foxglove.messages, the well-known schemas; frames in frames.py).

Point clouds are packed from numpy arrays in one ``tobytes`` (no loop over points); the scene has a handful of
entities (route, chosen point, setpoint, label), so building it costs the same whatever the obstacle count.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    FrameTransform,
    LinePrimitive,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PointCloud,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from apf_companion.navigator import State, StateChange
from apf_companion.observe import CycleSnapshot, PlanStep
from apf_companion.planning import Decision
from apf_companion.viz.frames import FRAME_ENU, FRAME_NED, NED_IN_ENU_XYZW, yaw_quaternion_xyzw

__all__ = [
    "candidate_cloud",
    "candidate_scores",
    "cycle_record",
    "frame_transform",
    "log_messages",
    "point_cloud",
    "pose",
    "scene",
    "stamp",
    "to3",
]

FloatArray = npt.NDArray[np.float64]
_F32 = PackedElementFieldNumericType.Float32
_XYZ = ("x", "y", "z")
_WARN_STATES = {State.HOLDING, State.STUCK, State.LINK_LOST}
_GREEN = Color(r=0.1, g=0.8, b=0.2, a=1.0)
_ORANGE = Color(r=1.0, g=0.55, b=0.0, a=1.0)
_MAGENTA = Color(r=0.9, g=0.1, b=0.9, a=1.0)
_WHITE = Color(r=1.0, g=1.0, b=1.0, a=1.0)
_IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def stamp(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _vec(p: FloatArray | tuple[float, ...]) -> Vector3:
    return Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _point(p: FloatArray) -> Point3:
    return Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _sphere(p: FloatArray, size_m: float, color: Color) -> SpherePrimitive:
    return SpherePrimitive(pose=Pose(position=_vec(p), orientation=_IDENTITY), size=_vec((size_m,) * 3), color=color)


def to3(points: FloatArray, down_m: float) -> FloatArray:
    """(N, D) points as (N, 3) local NED; 2D points get ``down_m``."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1] == 3:
        return pts.reshape(-1, 3)
    out = np.empty((pts.reshape(-1, pts.shape[-1]).shape[0], 3))
    out[:, :2] = pts.reshape(-1, 2)
    out[:, 2] = down_m
    return out


def frame_transform(ns: int) -> FrameTransform:
    """``enu`` -> ``ned`` (frames.py)."""
    x, y, z, w = NED_IN_ENU_XYZW
    return FrameTransform(
        timestamp=stamp(ns),
        parent_frame_id=FRAME_ENU,
        child_frame_id=FRAME_NED,
        translation=Vector3(x=0.0, y=0.0, z=0.0),
        rotation=Quaternion(x=x, y=y, z=z, w=w),
    )


def pose(snap: CycleSnapshot, ns: int) -> PoseInFrame | None:
    if snap.pose is None:
        return None
    x, y, z, w = yaw_quaternion_xyzw(snap.pose.yaw_rad)
    orientation = Quaternion(x=x, y=y, z=z, w=w)
    return PoseInFrame(
        timestamp=stamp(ns), frame_id=FRAME_NED, pose=Pose(position=_vec(snap.pose.pos_ned_m), orientation=orientation)
    )


def point_cloud(ns: int, xyz: FloatArray, extra: dict[str, FloatArray] | None = None) -> PointCloud:
    """(N, 3) points (and per-point float fields) as a packed float32 PointCloud in ``ned``."""
    extra = extra or {}
    names = (*_XYZ, *extra)
    cols = np.empty((xyz.shape[0], len(names)), dtype=np.float32)
    cols[:, :3] = xyz
    for i, values in enumerate(extra.values(), start=3):
        cols[:, i] = values
    fields = [PackedElementField(name=n, offset=4 * i, type=_F32) for i, n in enumerate(names)]
    return PointCloud(
        timestamp=stamp(ns),
        frame_id=FRAME_NED,
        pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=_IDENTITY),
        point_stride=4 * len(names),
        fields=fields,
        data=cols.tobytes(),
    )


def candidate_scores(plan: PlanStep) -> tuple[FloatArray, FloatArray]:
    """(score, cost_m) per candidate: score 1 = the best passing point, 0 = the worst, -1 = fails the move test
    (or no scores from this planner: all 0); cost_m the planner's J_k [m], NaN where it fails."""
    n = plan.candidates_m.shape[0]
    cost = plan.decision.candidate_cost if isinstance(plan.decision, Decision) else None
    if cost is None or cost.shape != (n,):
        return np.zeros(n), np.full(n, np.nan)
    passing = np.isfinite(cost)
    if not passing.any():
        return np.full(n, -1.0), np.full(n, np.nan)
    lo, hi = float(cost[passing].min()), float(cost[passing].max())
    with np.errstate(invalid="ignore"):
        score = np.where(passing, 1.0 - (cost - lo) / max(hi - lo, 1e-9), -1.0)
    return score, np.where(passing, cost, np.nan)


def candidate_cloud(snap: CycleSnapshot, ns: int) -> PointCloud | None:
    """The latest planner step's candidates with ``score`` and ``cost_m`` (2D steps at the flown altitude)."""
    if snap.plan is None:
        return None
    score, cost = candidate_scores(snap.plan)
    return point_cloud(ns, to3(snap.plan.candidates_m, _down(snap)), {"score": score, "cost_m": cost})


def _down(snap: CycleSnapshot) -> float:
    if snap.target_ned_m is not None and math.isfinite(float(snap.target_ned_m[2])):
        return float(snap.target_ned_m[2])
    return 0.0 if snap.pose is None else float(snap.pose.pos_ned_m[2])


def _route_entity(snap: CycleSnapshot, ns: int) -> SceneEntity:
    lines, spheres = [], []
    if snap.route is not None:
        wps = np.array(snap.route.waypoints_ned_m, dtype=np.float64)
        wps[:, 2] = np.where(np.isnan(wps[:, 2]), _down(snap), wps[:, 2])  # NaN down: the leg keeps its altitude
        start = [] if snap.pose is None else [snap.pose.pos_ned_m]
        pts = [_point(p) for p in [*start, *wps]]  # a few waypoints, not points of a cloud
        lines.append(LinePrimitive(thickness=0.06, points=pts, color=_GREEN))
        spheres.append(_sphere(wps[-1], 0.6, _GREEN))
    if snap.target_ned_m is not None:
        spheres.append(_sphere(np.nan_to_num(snap.target_ned_m, nan=_down(snap)), 0.35, _GREEN))
    return SceneEntity(timestamp=stamp(ns), frame_id=FRAME_NED, id="route", lines=lines, spheres=spheres)


def _chosen_entity(snap: CycleSnapshot, ns: int) -> SceneEntity:
    spheres, lines = [], []
    plan = snap.plan
    nxt = None if plan is None else plan.decision.next_point_m
    if plan is not None and nxt is not None:
        down = _down(snap)
        a, b = to3(plan.origin_m, down)[0], to3(nxt, down)[0]
        spheres.append(_sphere(b, 0.25, _ORANGE))
        lines.append(LinePrimitive(thickness=0.04, points=[_point(a), _point(b)], color=_ORANGE))
    return SceneEntity(timestamp=stamp(ns), frame_id=FRAME_NED, id="chosen", spheres=spheres, lines=lines)


def _arrow_orientation(v: FloatArray) -> Quaternion:
    """The rotation taking +x to the direction of ``v`` (arrows point along their pose's x axis)."""
    n = float(np.linalg.norm(v))
    u = v / n
    w = 1.0 + float(u[0])
    if w < 1e-9:  # opposite to +x: half a turn about z
        return Quaternion(x=0.0, y=0.0, z=1.0, w=0.0)
    q = np.array([0.0, -float(u[2]), float(u[1]), w])  # cross((1, 0, 0), u), 1 + dot
    q /= np.linalg.norm(q)
    return Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _setpoint_entity(snap: CycleSnapshot, ns: int) -> SceneEntity:
    spheres, arrows, texts = [], [], []
    sp = snap.out.setpoint
    if sp is not None:
        pos = np.array(sp.pos_ned_m)
        spheres.append(_sphere(pos, 0.2, _MAGENTA))
        vel = np.array(sp.vel_ned_m_s)
        speed = float(np.linalg.norm(vel))
        if speed > 1e-3:
            arrows.append(
                ArrowPrimitive(
                    pose=Pose(position=_vec(pos), orientation=_arrow_orientation(vel)),
                    shaft_length=speed,
                    shaft_diameter=0.05,
                    head_length=0.15,
                    head_diameter=0.15,
                    color=_MAGENTA,
                )
            )
    if snap.pose is not None:
        label = f"{snap.out.state.value} {snap.out.decision or ''}".strip()
        at = snap.pose.pos_ned_m + np.array([0.0, 0.0, -1.0])  # 1 m above the vehicle (z is down)
        texts.append(
            TextPrimitive(pose=Pose(position=_vec(at), orientation=_IDENTITY), billboard=True, font_size=14.0,
                          scale_invariant=True, color=_WHITE, text=label)
        )  # fmt: skip
    return SceneEntity(
        timestamp=stamp(ns), frame_id=FRAME_NED, id="setpoint", spheres=spheres, arrows=arrows, texts=texts
    )


def scene(snap: CycleSnapshot, ns: int) -> SceneUpdate:
    """Goal and route, the chosen point (and the move to it), the setpoint sent and a state label. The same
    entity ids every cycle: each replaces the last, an empty one clears it."""
    return SceneUpdate(entities=[_route_entity(snap, ns), _chosen_entity(snap, ns), _setpoint_entity(snap, ns)])


def _change_log(change: StateChange, ns: int) -> Log:
    level = LogLevel.Warning if change.new in _WARN_STATES else LogLevel.Info
    text = f"{change.old.value} -> {change.new.value}: {change.reason}"
    return Log(timestamp=stamp(ns), level=level, message=text, name="apf.state")


def log_messages(snap: CycleSnapshot, previous_decision: str | None, ns: int) -> list[Log]:
    """State changes (with their reasons) and a change of the planner's decision (GREEDY -> LOCAL_MINIMUM, ...;
    flying on to the chosen point, TRACKING, is no decision), as Log messages."""
    logs = [_change_log(c, ns) for c in snap.out.changes]
    decision = snap.out.decision
    if decision not in (None, "TRACKING", previous_decision):
        text = f"decision {previous_decision or '-'} -> {decision}"
        plan = snap.plan
        if plan is not None and isinstance(plan.decision, Decision):
            d = plan.decision
            text += f" (chosen {d.chosen_index}, {d.n_passing} of {plan.candidates_m.shape[0]} points pass)"
        logs.append(Log(timestamp=stamp(ns), level=LogLevel.Info, message=text, name="apf.planner"))
    return logs


def cycle_record(snap: CycleSnapshot) -> dict[str, Any]:
    """The per-cycle JSON (``/apf/cycle``): numbers for plots, names for the state panel."""
    out, sp, plan = snap.out, snap.out.setpoint, snap.plan
    rec: dict[str, Any] = {
        "t_s": out.t_s,
        "state": out.state.value,
        "decision": out.decision,
        "distance_to_goal_m": out.distance_to_goal_m,
        "nearest_obstacle_m": out.nearest_obstacle_m,
        "n_obstacles": int(snap.obstacles_ned_m.shape[0]),
        "n_scan_points": int(snap.scan_ned_m.shape[0]),
        "pose_ned_m": None if snap.pose is None else [float(v) for v in snap.pose.pos_ned_m],
        "yaw_rad": None if snap.pose is None else snap.pose.yaw_rad,
        "setpoint": None,
        "plan_seq": None if plan is None else plan.seq,
    }
    if sp is not None:
        rec["setpoint"] = {"kind": sp.kind.value, "pos_ned_m": sp.pos_ned_m, "vel_ned_m_s": sp.vel_ned_m_s}
    if plan is not None and isinstance(plan.decision, Decision):
        d = plan.decision
        rec |= {"reason": d.reason.name, "chosen_index": d.chosen_index, "n_passing": d.n_passing}
        rec["chosen_ned_m"] = (
            None if d.next_point_m is None else [float(v) for v in to3(d.next_point_m, _down(snap))[0]]
        )
    return rec
