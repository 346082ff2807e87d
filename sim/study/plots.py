"""The study's figures (matplotlib, Agg backend, PNG), after the paper's Figures 6-9.

- ``trajectories.png``: a successful and an unsuccessful CR-BAPF* run with the obstacles and their rho_l / rho_u
  circles (paper Fig. "Successful and unsuccessful navigation").
- ``rs_vs_mu.png``: R_s versus mu_o for BAPF and CR-BAPF* with 95 % intervals (needs ``--mu-sweep``).
- ``abapf_mu.png``: mu_o,k of the chosen point versus step for A-BAPF in one successful run, under the
  documented "paper" A-BAPF rule (``AbapfRule.PAPER``: the exact rule always gives mu_max, docs/paper/notes.md).
- ``rs_per_planner.png``: R_s per planner and density with 95 % intervals, the paper's values marked.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.planning import AbapfRule
from sim.study.config import Density, StudyConfig
from sim.study.engine import CellResult, Trace, chunk_generators, simulate
from sim.study.metrics import Outcome, summarize
from sim.study.paper import paper_row
from sim.study.worlds import WorldBatch, draw_worlds


@dataclass(frozen=True, slots=True, kw_only=True)
class ExampleRuns:
    """A small recorded batch of one planner, for trajectory figures."""

    config: StudyConfig
    planner_name: str
    worlds: WorldBatch
    outcome: npt.NDArray[np.int8]
    trace: Trace

    def path_m(self, trial: int) -> npt.NDArray[np.float64]:
        """(M, D) positions of one trial at the start of each of its iterations."""
        p = self.trace.positions_m[:, trial, :]
        return p[~np.isnan(p[:, 0])]

    def first(self, success: bool) -> int | None:
        hits = np.flatnonzero((self.outcome == Outcome.SUCCESS) == success)
        return int(hits[0]) if hits.size else None


def example_runs(
    config: StudyConfig, planner_name: str, density: Density, seed: int, n_trials: int = 64
) -> ExampleRuns:
    """Record ``n_trials`` trials of the first chunk's streams (same seeds as the study's chunk 0)."""
    world_rng, motion_rng = chunk_generators(seed, density, 0)
    worlds = draw_worlds(world_rng, n_trials, density, config.obstacle_box_m, config.dim, config.obstacle_sampling)
    result = simulate(config, planner_name, worlds, motion_rng, record=True)
    assert result.trace is not None
    return ExampleRuns(
        config=config,
        planner_name=planner_name,
        worlds=worlds,
        outcome=result.records.outcome,
        trace=result.trace,
    )


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectories(path: Path, runs: ExampleRuns) -> bool:
    """Successful and unsuccessful run side by side; False (no file) if either kind is missing."""
    ok, bad = runs.first(True), runs.first(False)
    if ok is None or bad is None:
        return False
    plt = _pyplot()
    params = runs.config.planner_params
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    for ax, trial, title in ((axes[0], ok, "successful"), (axes[1], bad, "unsuccessful")):
        obs = runs.worlds.obstacles_m[trial][runs.worlds.mask[trial]]
        for x, y in obs[:, :2]:
            ax.add_patch(plt.Circle((x, y), params.rho_u_m, fill=False, color="0.8", lw=0.6))
            ax.add_patch(plt.Circle((x, y), params.rho_l_m, fill=True, color="tab:red", alpha=0.35))
        ax.plot(obs[:, 0], obs[:, 1], "k.", ms=4, label="obstacle")
        p = runs.path_m(trial)
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1.2, label="path")
        sx, sy = runs.config.start_m[:2]
        tx, ty = runs.config.target_m[:2]
        ax.plot([sx], [sy], "go", label="start")
        ax.plot([tx], [ty], "r*", ms=12, label="target")
        ax.add_patch(plt.Circle((tx, ty), runs.config.goal_radius_m, fill=False, color="r", ls="--"))
        outcome = Outcome(int(runs.outcome[trial])).name.lower()
        ax.set_title(f"{runs.planner_name} {title} run ({outcome}, {p.shape[0]} iterations)")
        low, high = runs.config.obstacle_box_m
        lim = (min(0.0, low) - 1.0, max(30.0, high) + 1.0)
        ax.set_xlim(*lim)
        ax.set_ylim(*lim)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(
        f"{runs.config.preset} preset: grey circles rho_u = {params.rho_u_m} m, red discs rho_l = {params.rho_l_m} m"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def plot_mu_sweep(path: Path, sweep: Sequence[tuple[float, Sequence[CellResult]]]) -> None:
    """R_s versus mu_o, one line per (planner, density), 95 % Wilson intervals as error bars."""
    plt = _pyplot()
    series: dict[tuple[str, str], list[tuple[float, float, float, float]]] = {}
    for mu, cells in sweep:
        for cell in cells:
            s = summarize(cell.records)
            series.setdefault((cell.planner_name, cell.density.label), []).append(
                (mu, s.R_s, s.R_s - s.R_s_ci95[0], s.R_s_ci95[1] - s.R_s)
            )
    fig, ax = plt.subplots(figsize=(8, 5))
    for (name, label), pts in series.items():
        arr = np.array(sorted(pts))
        style = "-o" if name == "cr-bapf*" else "--s"
        ax.errorbar(arr[:, 0], arr[:, 1], yerr=arr[:, 2:].T, fmt=style, ms=4, capsize=2, label=f"{name} N {label}")
    ax.set_xlabel("mu_o (1/m^2)")
    ax.set_ylabel("R_s")
    ax.set_ylim(0.0, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Rate of success versus mu_o (95 % Wilson intervals)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def abapf_paper_rule_config(config: StudyConfig) -> StudyConfig:
    """The study with A-BAPF's documented "paper" rule (the exact rule gives mu_max at every step)."""
    params = dataclasses.replace(config.planner_params, abapf_rule=AbapfRule.PAPER)
    return dataclasses.replace(config, planner_params=params)


def plot_abapf_mu(path: Path, runs: ExampleRuns) -> bool:
    """mu_o,k of the chosen point versus navigation step for the first successful run; False if none."""
    trial = runs.first(True)
    if trial is None:
        return False
    mu = runs.trace.mu_o_k[:, trial]
    steps = np.flatnonzero(~np.isnan(mu))
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.step(steps + 1, mu[steps], where="mid", color="tab:purple")
    ax.set_xlabel("navigation step")
    ax.set_ylabel("mu_o,k of the selected point (1/m^2)")
    rule = runs.config.planner_params.abapf_rule.value
    ax.set_title(f"A-BAPF mu_o,k per step, one successful run ({rule!r} rule, {runs.config.preset} preset)")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def plot_rs_per_planner(path: Path, cells: Sequence[CellResult]) -> None:
    """Grouped bars: R_s per planner for each density, 95 % intervals, the paper's value as a black tick."""
    plt = _pyplot()
    planners = list(dict.fromkeys(c.planner_name for c in cells))
    densities = list(dict.fromkeys(c.density for c in cells))
    width = 0.8 / max(len(planners), 1)
    fig, ax = plt.subplots(figsize=(9, 5))
    x = np.arange(len(densities))
    for i, name in enumerate(planners):
        rs, lo, hi, paper = [], [], [], []
        for d in densities:
            cell = next((c for c in cells if c.planner_name == name and c.density == d), None)
            if cell is None:
                rs.append(np.nan)
                lo.append(0.0)
                hi.append(0.0)
                paper.append(np.nan)
                continue
            s = summarize(cell.records)
            rs.append(s.R_s)
            lo.append(s.R_s - s.R_s_ci95[0])
            hi.append(s.R_s_ci95[1] - s.R_s)
            p = paper_row(name, d.n_low, d.n_high)
            paper.append(p.R_s if p else np.nan)
        xs = x - 0.4 + width * (i + 0.5)
        ax.bar(xs, rs, width, yerr=[lo, hi], capsize=3, label=name)
        ax.plot(xs, paper, "k_", ms=14, mew=2)
    ax.plot([], [], "k_", ms=14, mew=2, label="paper (Table II)")
    ax.set_xticks(x, [f"N ~ U[{d.n_low}, {d.n_high}]" for d in densities])
    ax.set_ylabel("R_s")
    ax.set_ylim(0.0, 1.05)
    ax.legend(fontsize=8, ncols=2)
    ax.set_title("Rate of success per planner and density (95 % Wilson intervals)")
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
