"""Figures of the study's world files (``apf-sim study --world ... --plots DIR``): the true geometry, the surface
samples the planners see, the full-knowledge optimum and one example run of each planner."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sim.study.config import StudyConfig
from sim.study.engine import simulate
from sim.study.metrics import Outcome
from sim.study.optimal import optimal_path
from sim.study.worlds import WorldBatch
from sim.study.worldstudy import WorldCase, motion_generator, world_config
from sim.world.geometry import segment_clearance_m

__all__ = ["example_path", "plot_world"]


def example_path(config: StudyConfig, planner_name: str, case: WorldCase, seed: int) -> tuple[np.ndarray, str]:
    """One recorded trial of ``planner_name`` on ``case`` (its own seeded stream): (M, 2) positions, outcome."""
    samples = case.samples_ne_m
    batch = WorldBatch(obstacles_m=samples[None].copy(), mask=np.ones((1, samples.shape[0]), dtype=bool))
    world = case.world

    def clearance(from_ne_m: np.ndarray, to_ne_m: np.ndarray) -> np.ndarray:
        return segment_clearance_m(world, from_ne_m, to_ne_m)

    rng = motion_generator(seed, f"example:{case.label}", 0)
    res = simulate(world_config(config, world), planner_name, batch, rng, record=True, clearance=clearance)
    assert res.trace is not None
    p = res.trace.positions_m[:, 0, :]
    return p[~np.isnan(p[:, 0])], Outcome(int(res.records.outcome[0])).name.lower()


def plot_world(
    path: Path,
    case: WorldCase,
    config: StudyConfig,
    planners: Sequence[str],
    seed: int,
    *,
    clearance_m: float,
    resolution_m: float,
) -> None:
    """Write ``path`` (PNG): walls and trunks to scale, samples, start/goal, A* optimum, one run per planner."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    world = case.world
    fig, ax = plt.subplots(figsize=(7.0, 5.0), dpi=80)
    for (n, e), r in zip(world.circles_ne_m, world.circle_radii_m, strict=True):
        ax.add_patch(Circle((e, n), max(float(r), 0.05), color="0.2"))
    for (a, b), t in zip(world.walls_ne_m, world.wall_thickness_m, strict=True):
        # Line width in points from the thickness in metres at this axis scale is fiddly; draw a filled capsule.
        d = b - a
        length = float(np.hypot(*d))
        u = d / length if length > 0 else np.array([1.0, 0.0])
        nrm = np.array([-u[1], u[0]]) * max(float(t), 0.05) / 2.0
        quad = np.array([a + nrm, b + nrm, b - nrm, a - nrm])
        ax.fill(quad[:, 1], quad[:, 0], color="0.2", lw=0)
    s = case.samples_ne_m
    ax.plot(s[:, 1], s[:, 0], ".", ms=1.5, color="tab:orange", label="surface samples")
    opt = optimal_path(world, clearance_m=clearance_m, resolution_m=resolution_m)
    if opt.path_ne_m.size:
        ax.plot(opt.path_ne_m[:, 1], opt.path_ne_m[:, 0], "k--", lw=1.2, label=f"A* to the goal {opt.length_m:.1f} m")
    colours = plt.get_cmap("tab10")
    for k, name in enumerate(planners):
        pts, outcome = example_path(config, name, case, seed)
        ax.plot(pts[:, 1], pts[:, 0], "-", lw=1.0, color=colours(k % 10), label=f"{name}: {outcome}")
    assert world.start_ne_m is not None and world.goal_ne_m is not None
    ax.plot(world.start_ne_m[1], world.start_ne_m[0], "go", ms=6)
    ax.plot(world.goal_ne_m[1], world.goal_ne_m[0], "r*", ms=11)
    ax.add_patch(Circle((world.goal_ne_m[1], world.goal_ne_m[0]), config.goal_radius_m, fill=False, color="r"))
    ax.set_title(f"{case.label}", fontsize=10)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
