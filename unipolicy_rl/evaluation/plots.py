"""Pictures of a policy: design-grid heatmaps and a training curve, written as PNG files.

Figures are built with matplotlib's object API (``Figure``, drawn by Agg) rather than
pyplot, so plots work on headless machines and importing this module never switches the
backend of a user's notebook or GUI session. Matplotlib is imported where a figure is drawn, not
with this module: every command imports it (train.py, evaluate), and matplotlib's import is about a
second of each command's start.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from unipolicy_rl.evaluation.grid import DesignResult
from unipolicy_rl.metric_columns import DISPLACEMENT, EPOCH, EVAL_RETURN, GRID_MEAN, GRID_MIN, REAL_STEPS, REWARD

# (attribute of DesignResult, file stem, colour-bar label)
HEATMAPS = (
    ("mean_episode_reward", "heatmap_reward", "mean episode reward"),
    ("mean_forward_displacement", "heatmap_displacement", "mean forward displacement (m)"),
)


def design_grid(results: Sequence[DesignResult], metric: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lengths, densities, values[density, length]) of ``metric``; cells not evaluated are NaN."""
    lengths = np.array(sorted({r.length for r in results}))
    densities = np.array(sorted({r.density for r in results}))
    values = np.full((len(densities), len(lengths)), np.nan)
    for result in results:
        row, column = np.searchsorted(densities, result.density), np.searchsorted(lengths, result.length)
        values[row, column] = getattr(result, metric)
    return lengths, densities, values


def plot_heatmaps(results: Sequence[DesignResult], out_dir: str | Path, title: str = "") -> list[Path]:
    """Writes ``heatmap_reward.png`` and ``heatmap_displacement.png`` into ``out_dir``; returns their paths.

    Length runs along x and density along y, one annotated cell per design, so the
    region where the policy stops walking is visible at a glance.
    """
    if not results:
        raise ValueError("results is empty: nothing to plot")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    from matplotlib.figure import Figure

    for metric, stem, label in HEATMAPS:
        lengths, densities, values = design_grid(results, metric)
        figure = Figure(figsize=(1.1 * len(lengths) + 3.0, 0.9 * len(densities) + 2.0))
        axes = figure.subplots()
        image = axes.imshow(values, origin="lower", cmap="viridis", aspect="auto")
        figure.colorbar(image, ax=axes, label=label)
        _annotate_cells(axes, image, values)
        axes.set_xticks(range(len(lengths)), [f"{length:.3f}" for length in lengths])
        axes.set_yticks(range(len(densities)), [f"{density:.3f}" for density in densities])
        axes.set_xlabel("link length l (m)")
        axes.set_ylabel("link density rho (kg/m)")
        axes.set_title(f"{title}: {label}" if title else label)
        figure.tight_layout()
        path = out_dir / f"{stem}.png"
        figure.savefig(path, dpi=120)
        paths.append(path)
    return paths


def _annotate_cells(axes, image, values: np.ndarray) -> None:
    # Dark text on light cells, light text on dark ones, so every number stays legible.
    for (row, column), value in np.ndenumerate(values):
        if math.isnan(value):
            continue
        red, green, blue, _ = image.cmap(image.norm(value))
        colour = "black" if 0.299 * red + 0.587 * green + 0.114 * blue > 0.5 else "white"
        axes.text(column, row, f"{value:.2f}", ha="center", va="center", color=colour, fontsize=9)


def plot_training_curve(csv_path_or_rows: str | Path | Iterable[Mapping], out_path: str | Path) -> Path:
    """Real episode reward (and forward displacement, the periodic grid evaluation, or a gym task's
    evaluation return, when logged) from a metrics CSV or its rows, against real env steps when
    logged, else epochs.

    Reads columns ``epoch``, ``train/episode_reward``, and where they are logged ``real_env_steps``,
    ``train/forward_displacement``, ``eval/grid_mean_displacement``, ``eval/grid_min_displacement``
    and ``eval/mean_return``. Blank cells (a metric not logged on that row, as on a model-based
    run's imagined rows, or a gym epoch in which no episode ended) are skipped, so only real returns
    are drawn; a panel with nothing to draw is left out.
    """
    rows = _read_rows(csv_path_or_rows)
    x_column, x_label = (REAL_STEPS, "real env steps") if any(
        _number(row.get(REAL_STEPS)) is not None for row in rows) else (EPOCH, "epoch")
    candidates = [((REWARD,), "episode reward"), ((DISPLACEMENT,), "forward displacement (m)"),
                  ((GRID_MEAN, GRID_MIN), "design grid (m)"), ((EVAL_RETURN,), "evaluation return")]
    panels = [(columns, label) for columns, label in candidates
              if any(_number(row.get(columns[0])) is not None and _number(row.get(x_column)) is not None
                     for row in rows)]
    if not panels:
        raise ValueError(f"no rows with both {x_column!r} and {REWARD!r} or {EVAL_RETURN!r}: is this a metrics CSV?")
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7, 3 * len(panels)))
    axes = figure.subplots(len(panels), 1, sharex=True, squeeze=False)
    for axis, (columns, label) in zip(axes[:, 0], panels, strict=True):
        for column in columns:
            points = [(_number(row.get(x_column)), _number(row.get(column))) for row in rows]
            points = [(x, value) for x, value in points if x is not None and value is not None]
            name = column.split("/")[-1].replace("grid_", "").replace("_displacement", "")
            axis.plot([x for x, _ in points], [value for _, value in points], marker="." if len(points) < 50 else "",
                      label=name if len(columns) > 1 else None)
        if len(columns) > 1:
            axis.legend(loc="best", fontsize=8)
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(x_label)
    figure.tight_layout()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out_path, dpi=120)
    return out_path


def _read_rows(csv_path_or_rows) -> list[Mapping]:
    if isinstance(csv_path_or_rows, (str, Path)):
        with Path(csv_path_or_rows).open(newline="") as handle:
            return list(csv.DictReader(handle))
    return list(csv_path_or_rows)


def _number(value) -> float | None:
    if value is None or value == "":
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None
