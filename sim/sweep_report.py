"""Output of ``apf-sim sweep``: a markdown table, ``sweep.csv``, ``sweep.json`` and heatmaps (matplotlib, Agg).

One row per (planner, grid point, scenario); a scenario is a density (``n_low``, ``n_high``) or a world (``world``),
the other columns are empty (CSV) or null (JSON). Heatmaps: one PNG per planner, rows = grid points, columns =
scenarios (densities, then worlds, as given), two panels: R_s and the mean path length of successful trials.
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sim.study.config import Density, StudyConfig
from sim.sweep import SweepCell, scenario_label
from sim.sweep_grid import SweepParam, format_value, point_label

JSON_SCHEMA_VERSION = 2
"""2: a ``world`` key in every row (null on densities; ``n_low``/``n_high`` null on worlds)."""

CSV_FIELDS_BEFORE = ("planner", "world", "n_low", "n_high")
CSV_FIELDS_AFTER = (
    "trials",
    "R_s",
    "R_s_ci95_low",
    "R_s_ci95_high",
    "M_s",
    "path_length_m",
    "S_m",
    "success",
    "collision",
    "stuck",
    "timeout",
)


def _num(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def _fmt(x: float, digits: int) -> str:
    return "–" if math.isnan(x) else f"{x:.{digits}f}"


def cell_row(cell: SweepCell) -> dict[str, Any]:
    s = cell.summary
    density = cell.scenario if isinstance(cell.scenario, Density) else None
    row: dict[str, Any] = {
        "planner": cell.planner_name,
        "world": None if density is not None else cell.scenario.label,
        "n_low": None if density is None else density.n_low,
        "n_high": None if density is None else density.n_high,
    }
    row.update({k: format_value(v) for k, v in cell.point.items()})
    row.update(
        {
            "trials": s.trials,
            "R_s": s.R_s,
            "R_s_ci95_low": s.R_s_ci95[0],
            "R_s_ci95_high": s.R_s_ci95[1],
            "M_s": _num(s.M_s),
            "path_length_m": _num(cell.mean_path_length_m),
            "S_m": _num(s.S),
            "success": s.success,
            "collision": s.collision,
            "stuck": s.stuck,
            "timeout": s.timeout,
        }
    )
    return row


def markdown_table(cells: Sequence[SweepCell]) -> str:
    head = "| planner | parameters | N or world | trials | R_s [95% CI] | M_s | path length (m) | S (m) |"
    lines = [head, "|" + "---|" * 8]
    for c in cells:
        s = c.summary
        lines.append(
            f"| {c.planner_name} | {point_label(c.point)} | {c.scenario.label} | {s.trials} | "
            f"{s.R_s:.3f} [{s.R_s_ci95[0]:.3f}, {s.R_s_ci95[1]:.3f}] | {_fmt(s.M_s, 1)} | "
            f"{_fmt(c.mean_path_length_m, 2)} | {_fmt(s.S, 2)} |"
        )
    return "\n".join(lines)


def write_csv(path: Path, cells: Sequence[SweepCell], swept: Sequence[SweepParam]) -> None:
    fields = [*CSV_FIELDS_BEFORE, *(p.field for p in swept), *CSV_FIELDS_AFTER]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        for c in cells:
            row = cell_row(c)
            writer.writerow({k: "" if row[k] is None else row[k] for k in fields})


def sweep_json(
    config: StudyConfig,
    cells: Sequence[SweepCell],
    swept: Sequence[SweepParam],
    *,
    seed: int,
    trials: int,
    wall_s: float,
    executor: dict[str, Any],
) -> dict[str, Any]:
    return {
        "schema": JSON_SCHEMA_VERSION,
        "preset": config.preset,
        "seed": seed,
        "trials_per_cell": trials,
        "wall_s": wall_s,
        "executor": executor,
        "grid": [{"field": p.field, "values": [format_value(v) for v in p.values]} for p in swept],
        "rows": [cell_row(c) for c in cells],
    }


def write_json(path: Path, document: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2, allow_nan=False) + "\n")


def _file_stem(planner_name: str) -> str:
    return re.sub(r"[^a-z0-9-]+", "-", planner_name.replace("*", "-star")).strip("-")


def _grid(cells: Sequence[SweepCell]) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    """Row labels (grid points), column labels (scenarios), and the R_s and path-length matrices."""
    rows = list(dict.fromkeys(point_label(c.point) for c in cells))
    cols = list(dict.fromkeys(scenario_label(c.scenario) for c in cells))
    rs = np.full((len(rows), len(cols)), np.nan)
    length = np.full_like(rs, np.nan)
    for c in cells:
        i, j = rows.index(point_label(c.point)), cols.index(scenario_label(c.scenario))
        rs[i, j] = c.summary.R_s
        length[i, j] = c.mean_path_length_m
    return rows, cols, rs, length


def _panel(fig: Any, ax: Any, data: np.ndarray, cmap: str, limits: tuple[float, float] | None) -> None:
    """One heatmap with its colour bar and, when small enough to read, the values written in the cells."""
    if limits is None:
        limits = (float(np.nanmin(data)), float(np.nanmax(data))) if np.isfinite(data).any() else (0.0, 1.0)
    im = ax.imshow(np.ma.masked_invalid(data), cmap=cmap, vmin=limits[0], vmax=limits[1], aspect="auto")
    if data.size <= 120:
        for (i, j), v in np.ndenumerate(data):
            r, g, b, _ = im.cmap(im.norm(v)) if not math.isnan(v) else (1.0, 1.0, 1.0, 1.0)
            ink = "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "white"
            ax.text(j, i, "–" if math.isnan(v) else f"{v:.2f}", ha="center", va="center", fontsize=7, color=ink)
    fig.colorbar(im, ax=ax, shrink=0.8)


def plot_heatmaps(out_dir: Path, cells: Sequence[SweepCell]) -> list[Path]:
    """One ``heatmap_<planner>.png`` per planner; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for planner_name in dict.fromkeys(c.planner_name for c in cells):
        rows, cols, rs, length = _grid([c for c in cells if c.planner_name == planner_name])
        size = (4.0 + 2.2 * len(cols), 1.8 + 0.35 * len(rows))
        fig, axes = plt.subplots(1, 2, figsize=size, constrained_layout=True, squeeze=False)
        panels = ((rs, "R_s", "viridis", (0.0, 1.0)), (length, "mean path length (m), successes", "magma_r", None))
        for k, (ax, (data, title, cmap, limits)) in enumerate(zip(axes[0], panels, strict=True)):
            _panel(fig, ax, data, cmap, limits)
            ax.set_xticks(range(len(cols)), cols, rotation=30 if len(cols) > 4 else 0)
            ax.set_yticks(range(len(rows)), rows if k == 0 else [""] * len(rows))
            ax.set_title(f"{planner_name}: {title}", fontsize=9)
        path = out_dir / f"heatmap_{_file_stem(planner_name)}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written
