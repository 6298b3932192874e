"""The report's figures: training curves with seed bands and design-grid heatmaps, one panel per source.

Like :mod:`unipolicy_rl.evaluation.plots`, figures are matplotlib ``Figure`` objects drawn by
Agg, never pyplot, so the report runs headless and leaves a notebook's backend alone. Every
panel of a figure shares one colour scale or one set of axes, so sources compare by eye.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from unipolicy_rl.evaluation import WALKING_DISPLACEMENT
from unipolicy_rl.report.bands import seed_band
from unipolicy_rl.report.grids import GridValues
from unipolicy_rl.report.metrics import Series
from unipolicy_rl.training.metrics_file import DISPLACEMENT, GRID_MEAN, GRID_MIN, REWARD

DPI = 120
# (columns drawn in one panel, line styles, y label); the grid panel only when a run logged it.
CURVE_PANELS = (
    ((REWARD,), ("-",), "episode reward (real env)"),
    ((DISPLACEMENT,), ("-",), "forward displacement (m)"),
    ((GRID_MEAN, GRID_MIN), ("-", "--"), "design-grid evaluation (m)\nmean solid, worst design dashed"),
)
X_LABELS = {"steps": "real env steps", "seconds": "wall time"}


def plot_curves(curves: Mapping[str, Mapping[str, Sequence[Series]]], axis: str, path: Path) -> Path:
    """``curves[label][column]`` holds one Series per seed; draws mean and 95% band per label
    against ``axis`` ("steps" or "seconds")."""
    panels = [panel for panel in CURVE_PANELS
              if any(curves[label].get(name) for label in curves for name in panel[0])]
    seconds = [float(np.nanmax(s.seconds)) for by_column in curves.values() for runs in by_column.values()
               for s in runs if np.isfinite(s.seconds).any()]
    scale, unit = (60.0, "min") if axis == "seconds" and seconds and max(seconds) > 600 else (1.0, "s")
    figure = Figure(figsize=(7.5, 2.8 * len(panels) + 0.6), layout="constrained")
    axes = figure.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    colours = _colours(curves)
    for ax, (names, styles, ylabel) in zip(axes, panels, strict=True):
        for label, by_column in curves.items():
            for name, style in zip(names, styles, strict=True):
                runs = by_column.get(name, [])
                band = seed_band([(x / (scale if axis == "seconds" else 1.0), y)
                                  for x, y in (s.against(axis) for s in runs)])
                if band is None:
                    continue
                seeds = int(band.seeds.max())
                ax.plot(band.x, band.mean, style, color=colours[label], marker="." if len(band.x) < 30 else "",
                        label=f"{label} ({seeds} seed{'s' if seeds != 1 else ''})" if style == "-" else None)
                ax.fill_between(band.x, band.low, band.high, color=colours[label], alpha=0.2, linewidth=0)
        if ylabel.startswith(("forward", "design")):
            ax.axhline(WALKING_DISPLACEMENT, color="grey", linewidth=0.8, linestyle=":")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[0].set_title("mean over seeds, shaded: 95% confidence band of the mean")
    xlabel = f"{X_LABELS[axis]} ({unit})" if axis == "seconds" else X_LABELS[axis]
    if axis == "steps" and _spans_decades(curves):
        # A model-based source walks on a small share of a model-free one's real steps: on a
        # linear axis its whole curve would sit in the first few pixels.
        axes[-1].set_xscale("log")
        xlabel += " (log scale)"
    axes[-1].set_xlabel(xlabel)
    return _save(figure, path)


def _spans_decades(curves: Mapping[str, Mapping[str, Sequence[Series]]], ratio: float = 5.0) -> bool:
    """Whether one source's runs end ``ratio`` times further along in real env steps than another's."""
    ends = []
    for by_column in curves.values():
        last = [float(np.nanmax(s.steps)) for runs in by_column.values() for s in runs if np.isfinite(s.steps).any()]
        if last:
            ends.append(max(last))
    return len(ends) > 1 and min(ends) > 0 and max(ends) / min(ends) >= ratio


@dataclass
class Panel:
    """One heatmap: a title, the grid, the design range trained on ((l_low, l_high), (rho_low,
    rho_high)) to outline when the grid leaves it, and cells to star."""

    title: str
    grid: GridValues
    training: tuple[tuple[float, float], tuple[float, float]] | None = None
    starred: set[tuple[int, int]] = field(default_factory=set)


def plot_heatmaps(panels: Sequence[Panel], path: Path, label: str, number_format: str = "{:.2f}",
                  cmap: str = "viridis", vmin: float | None = None, vmax: float | None = None,
                  note: str = "") -> Path:
    """One heatmap per panel on a shared colour scale, length along x and density along y,
    every cell annotated, the worst cell boxed in red and the training range outlined in white."""
    if not panels:
        raise ValueError("no panels to plot")
    finite = np.concatenate([panel.grid.values[np.isfinite(panel.grid.values)] for panel in panels])
    vmin = vmin if vmin is not None else (float(finite.min()) if len(finite) else 0.0)
    vmax = vmax if vmax is not None else (float(finite.max()) if len(finite) else 1.0)
    columns = min(len(panels), 3)
    rows = math.ceil(len(panels) / columns)
    width = max(len(panel.grid.lengths) for panel in panels)
    height = max(len(panel.grid.densities) for panel in panels)
    figure = Figure(figsize=(columns * (0.75 * width + 1.6) + 1.2, rows * (0.6 * height + 1.4) + 0.5),
                    layout="constrained")
    axes = figure.subplots(rows, columns, squeeze=False).ravel()
    image = None
    for ax, panel in zip(axes, panels, strict=False):
        grid = panel.grid
        image = ax.imshow(np.ma.masked_invalid(grid.values), origin="lower", cmap=cmap, vmin=vmin, vmax=vmax,
                          aspect="auto")
        _annotate(ax, image, grid.values, number_format, panel.starred)
        worst = grid.worst()
        if worst is not None:
            ax.add_patch(Rectangle((worst[1] - 0.5, worst[0] - 0.5), 1, 1, fill=False, edgecolor="red",
                                   linewidth=2.5))
        if panel.training is not None:
            _outline(ax, grid, panel.training)
        ax.set_xticks(range(len(grid.lengths)), [f"{length:.4g}" for length in grid.lengths], fontsize=7)
        ax.set_yticks(range(len(grid.densities)), [f"{density:.4g}" for density in grid.densities], fontsize=7)
        ax.set_xlabel("link length l (m)")
        ax.set_ylabel("link density rho (kg/m)")
        ax.set_title(panel.title, fontsize=9)
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    figure.colorbar(image, ax=axes[: len(panels)].tolist(), label=label, shrink=0.9)
    figure.suptitle("red box: worst design; white outline: designs trained on" + (f"\n{note}" if note else ""),
                    fontsize=9)
    return _save(figure, path)


def _annotate(ax, image, values: np.ndarray, number_format: str, starred: set[tuple[int, int]]) -> None:
    # Dark text on light cells, light on dark, as the per-run heatmaps do.
    for (row, column), value in np.ndenumerate(values):
        star = "*" if (row, column) in starred else ""
        if not math.isfinite(value):
            ax.text(column, row, "n/a" + star, ha="center", va="center", color="grey", fontsize=7)
            continue
        red, green, blue, _ = image.cmap(image.norm(value))
        colour = "black" if 0.299 * red + 0.587 * green + 0.114 * blue > 0.5 else "white"
        ax.text(column, row, number_format.format(value) + star, ha="center", va="center", color=colour, fontsize=7)


def _outline(ax, grid: GridValues, training) -> None:
    """The training range in cell coordinates, drawn only when the grid reaches beyond it."""
    (l_low, l_high), (d_low, d_high) = training
    tolerance = 1e-9
    leaves = (grid.lengths.min() < l_low - tolerance or grid.lengths.max() > l_high + tolerance
              or grid.densities.min() < d_low - tolerance or grid.densities.max() > d_high + tolerance)
    if not leaves or len(grid.lengths) < 2 or len(grid.densities) < 2:
        return
    x_low, x_high = _index(grid.lengths, l_low), _index(grid.lengths, l_high)
    y_low, y_high = _index(grid.densities, d_low), _index(grid.densities, d_high)
    if x_low == x_high and y_low == y_high:  # one design (DE): a marker, not a box
        ax.plot([x_low], [y_low], marker="o", markersize=18, markerfacecolor="none", markeredgecolor="white",
                markeredgewidth=2)
    else:
        ax.add_patch(Rectangle((x_low, y_low), x_high - x_low, y_high - y_low, fill=False, edgecolor="white",
                               linewidth=2, linestyle="--"))


def _index(axis_values: np.ndarray, value: float) -> float:
    """Position of ``value`` in cell units on an evenly spaced axis, extrapolated past its ends."""
    return float((value - axis_values[0]) / (axis_values[-1] - axis_values[0]) * (len(axis_values) - 1))


def _colours(labels) -> dict[str, tuple]:
    palette = colormaps["tab10"]
    return {label: palette(i % 10) for i, label in enumerate(sorted(labels))}


def _save(figure: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=DPI)
    return path
