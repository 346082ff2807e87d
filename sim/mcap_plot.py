"""``apf-sim mcap-plot FILE -o PNG``: a recorded flight (the service's MCAP) drawn with matplotlib.

What the Foxglove app's 3D panel shows, from above (east right, north up), at one moment: the remembered obstacle
points, the newest scan, the flown path, the route and goal, the candidate points coloured by score (crosses: they
fail the move test), the chosen point and the setpoint; below it the distance to the goal and to the nearest
obstacle over the flight, with the planner's decision. For the docs and for machines without the app.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.viz import Topic
from sim.extras import require

__all__ = ["Recording", "plot_recording", "read_recording", "register"]

FloatArray = npt.NDArray[np.float64]


@dataclass
class Recording:
    """The messages of one recording by topic, decoded, each with its log time [ns], in log-time order."""

    topics: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)

    def at(self, topic: Topic, t_ns: int) -> Any:
        """The last message on ``topic`` logged at or before ``t_ns`` (None if none)."""
        best = None
        for t, msg in self.topics.get(topic, []):
            if t > t_ns:
                break
            best = msg
        return best


def read_recording(path: Path) -> Recording:
    """Read an MCAP written by the service (protobuf via mcap-protobuf-support, the cycle record as JSON)."""
    from mcap.decoder import DecoderFactory as _Base
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    class _Json(_Base):
        def decoder_for(self, message_encoding: str, schema: Any) -> Callable[[bytes], Any] | None:
            return json.loads if message_encoding == "json" else None

    rec = Recording()
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), _Json()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            rec.topics.setdefault(channel.topic, []).append((message.log_time, decoded))
    return rec


def cloud_columns(cloud: Any, names: tuple[str, ...]) -> FloatArray:
    """(N, len(names)) float64 columns of a float32 foxglove.PointCloud."""
    if cloud is None or not cloud.data:
        return np.empty((0, len(names)))
    fields = [f.name for f in cloud.fields]
    table = np.frombuffer(cloud.data, dtype=np.float32).reshape(-1, cloud.point_stride // 4)
    return np.asarray(table[:, [fields.index(n) for n in names]], dtype=np.float64)


def _moment(rec: Recording, at_s: float | None) -> int:
    """The log time to draw: ``at_s`` after the first cycle, default the middle planner step."""
    cycles = rec.topics.get(Topic.CYCLE, [])
    if not cycles:
        raise ValueError("no /apf/cycle messages: not a recording of apf-companion")
    if at_s is not None:
        return cycles[0][0] + int(at_s * 1e9)
    planned = [t for t, c in cycles if c.get("decision") not in (None, "TRACKING")]
    times = planned or [t for t, _ in cycles]
    return times[len(times) // 2]


def _plot_scene(ax: Any, rec: Recording, t_ns: int, *, zoom_m: float | None = None) -> None:
    """The scene from above; ``zoom_m``: a window of that half-width around the vehicle (the candidates)."""
    obstacles = cloud_columns(rec.at(Topic.OBSTACLES, t_ns), ("x", "y"))
    scan = cloud_columns(rec.at(Topic.SCAN, t_ns), ("x", "y"))
    ax.scatter(obstacles[:, 1], obstacles[:, 0], s=18, c="0.55", marker="s", label="remembered obstacles")
    ax.scatter(scan[:, 1], scan[:, 0], s=3, c="tab:red", label="newest scan")
    cycles = [c for t, c in rec.topics.get(Topic.CYCLE, []) if c.get("pose_ned_m")]
    path = np.array([c["pose_ned_m"] for c in cycles])
    if path.size:
        ax.plot(path[:, 1], path[:, 0], "-", color="tab:blue", lw=1.0, alpha=0.6, label="flown path")
    cycle = rec.at(Topic.CYCLE, t_ns) or {}
    if cycle.get("pose_ned_m"):
        ax.plot(cycle["pose_ned_m"][1], cycle["pose_ned_m"][0], "o", color="tab:blue", ms=7, label="vehicle")
    cand = cloud_columns(rec.at(Topic.CANDIDATES, t_ns), ("x", "y", "score"))
    passing = cand[:, 2] >= 0.0
    ax.scatter(cand[~passing, 1], cand[~passing, 0], marker="x", s=14, c="0.6", lw=0.8, label="candidate: fails")
    sc = ax.scatter(cand[passing, 1], cand[passing, 0], s=22, c=cand[passing, 2], cmap="turbo", vmin=0.0, vmax=1.0)
    if zoom_m is not None:
        ax.figure.colorbar(sc, ax=ax, shrink=0.8, label="candidate score (1 = best)")
    if cycle.get("chosen_ned_m"):
        ax.plot(cycle["chosen_ned_m"][1], cycle["chosen_ned_m"][0], "*", color="tab:orange", ms=14, label="chosen")
    sp = cycle.get("setpoint")
    if sp:
        ax.plot(sp["pos_ned_m"][1], sp["pos_ned_m"][0], "D", color="m", ms=6, mfc="none", label="setpoint")
    scene = rec.at(Topic.SCENE, t_ns)
    for entity in [] if scene is None else scene.entities:
        for line in entity.lines if entity.id == "route" else []:
            ax.plot([p.y for p in line.points], [p.x for p in line.points], "--", color="tab:green", lw=1.0)
        for sphere in entity.spheres[:1] if entity.id == "route" else []:
            ax.plot(sphere.pose.position.y, sphere.pose.position.x, "*", color="tab:green", ms=16, label="goal")
    t_s = cycle.get("t_s", 0.0)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    if zoom_m is not None and cycle.get("pose_ned_m"):
        n, e = cycle["pose_ned_m"][:2]
        ax.set_xlim(e - zoom_m, e + zoom_m)
        ax.set_ylim(n - zoom_m, n + zoom_m)
        ax.set_title(f"around the vehicle: {cycle.get('n_passing', '?')} of {len(cand)} candidates pass", fontsize=10)
    else:
        ax.set_title(f"t = {t_s:.1f} s: {cycle.get('state', '?')}, {cycle.get('decision') or '-'}", fontsize=10)
        ax.legend(loc="upper left", fontsize=7, markerscale=0.8)


def _plot_timeline(ax: Any, rec: Recording, t_ns: int) -> None:
    cycles = [c for _, c in rec.topics.get(Topic.CYCLE, [])]
    t = np.array([c["t_s"] for c in cycles])
    goal = np.array([np.nan if c["distance_to_goal_m"] is None else c["distance_to_goal_m"] for c in cycles])
    near = np.array([np.nan if c["nearest_obstacle_m"] is None else c["nearest_obstacle_m"] for c in cycles])
    ax.plot(t, goal, color="tab:green", label="distance to goal [m]")
    ax.plot(t, near, color="0.3", label="nearest obstacle [m]")
    stuck = np.array([c["decision"] in ("LOCAL_MINIMUM", "GAVE_UP", "RANDOM_WALK") for c in cycles])
    if stuck.any():
        ax.plot(t[stuck], near[stuck], "|", color="tab:red", label="no greedy move")
    now = rec.at(Topic.CYCLE, t_ns)
    if now is not None:
        ax.axvline(now["t_s"], color="tab:orange", lw=1.0)
    ax.set_xlabel("service time [s]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize=7)


def plot_recording(path: Path, out: Path, *, at_s: float | None = None) -> None:
    """Draw ``path`` (an MCAP) into ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = read_recording(path)
    t_ns = _moment(rec, at_s)
    fig = plt.figure(figsize=(12.0, 8.0), dpi=100)
    grid = fig.add_gridspec(2, 2, height_ratios=(3, 1), width_ratios=(1, 1.1))
    _plot_scene(fig.add_subplot(grid[0, 0]), rec, t_ns)
    _plot_scene(fig.add_subplot(grid[0, 1]), rec, t_ns, zoom_m=2.0)
    _plot_timeline(fig.add_subplot(grid[1, :]), rec, t_ns)
    fig.suptitle(f"{path.name}", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def _cmd(args: argparse.Namespace) -> int:
    try:
        require("apf-sim mcap-plot", "mcap", "mcap_protobuf", "matplotlib")
    except ConfigError as err:
        print(err, file=sys.stderr)
        return 2
    try:
        plot_recording(args.file, args.output, at_s=args.at)
    except (OSError, ValueError, ImportError) as err:
        print(f"apf-sim mcap-plot: {args.file}: {err}", file=sys.stderr)
        return 1
    print(f"wrote {args.output}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser("mcap-plot", help="draw a recorded flight (.mcap) to PNG", description=__doc__)
    p.add_argument("file", type=Path, help="an .mcap written by the service ([visualisation] mcap_dir)")
    p.add_argument("-o", "--output", type=Path, required=True, help="PNG to write")
    p.add_argument("--at", type=float, help="the moment to draw, seconds after the first cycle (default: mid-flight)")
    p.set_defaults(func=_cmd)
