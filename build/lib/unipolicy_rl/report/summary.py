"""The summary table: one row per source, every figure a mean and a spread over its seeds.

Per-run grid numbers come from :func:`unipolicy_rl.evaluation.summarise`, the same function
that prints a run's own summary line, so the table and the training log never disagree. The
table is written twice: formatted in report.md, and as plain numbers in summary.csv for
anything (docs/results.md) that quotes it.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from unipolicy_rl.evaluation import DesignResult, summarise
from unipolicy_rl.report.metrics import first_walking, median_to_walk, surrogate_figures
from unipolicy_rl.report.runs import Run


@dataclass
class SourceSummary:
    """Per-seed numbers of one source; lists hold one value per finished run (seed)."""

    label: str
    runs: int
    finished: int
    mean_reward: list[float] = field(default_factory=list)  # over the design grid
    worst_reward: list[float] = field(default_factory=list)  # the grid's worst design
    mean_displacement: list[float] = field(default_factory=list)
    worst_displacement: list[float] = field(default_factory=list)
    walking_designs: list[int] = field(default_factory=list)
    designs: int = 0
    logged_runs: int = 0  # runs with real training episodes logged, the base of the two below
    steps_to_walk: list[float] = field(default_factory=list)  # runs that reached walking only
    seconds_to_walk: list[float] = field(default_factory=list)
    wide_walking: list[float] = field(default_factory=list)  # share of the wider grid that walks
    surrogate: dict[str, list[float]] = field(default_factory=dict)


def summarise_source(label: str, runs: Sequence[Run], wide: Mapping[str, Sequence[DesignResult]]) -> SourceSummary:
    """``wide`` maps a run's name to its results on the wider grid, where it has them."""
    finished = [run for run in runs if run.finished]
    summary = SourceSummary(label, len(runs), len(finished))
    for run in finished:
        grid = summarise(run.designs)
        summary.mean_reward.append(grid["mean_episode_reward"])
        summary.worst_reward.append(grid["min_episode_reward"])
        summary.mean_displacement.append(grid["mean_forward_displacement"])
        summary.worst_displacement.append(grid["min_forward_displacement"])
        summary.walking_designs.append(grid["walking_designs"])
        summary.designs = max(summary.designs, grid["designs"])
        if run.name in wide:
            summary.wide_walking.append(summarise(wide[run.name])["walking_fraction"])
    for run in runs:
        if not run.rows:
            continue
        summary.logged_runs += 1
        reached = first_walking(run)
        if reached is not None:
            summary.steps_to_walk.append(reached[0])
            summary.seconds_to_walk.append(reached[1])
        for name, value in surrogate_figures(run).items():
            summary.surrogate.setdefault(name, []).append(value)
    return summary


# -- formatting ------------------------------------------------------------------------
TABLE_HEADER = ("source", "seeds finished", "mean reward", "worst-design reward", "mean displacement (m)",
                "worst-design displacement (m)", "designs walking", "real env steps to walk the grid",
                "wall time to walk the grid", "wider grid walking")


def table_row(summary: SourceSummary) -> list[str]:
    walking = (f"{_mean(summary.walking_designs):.1f}/{summary.designs}" if summary.walking_designs else "-")
    return [
        summary.label,
        f"{summary.finished}/{summary.runs}",
        _mean_spread(summary.mean_reward, "{:.1f}"),
        _mean_spread(summary.worst_reward, "{:.1f}"),
        _mean_spread(summary.mean_displacement, "{:.2f}"),
        _mean_spread(summary.worst_displacement, "{:.2f}"),
        walking,
        _reached(summary.steps_to_walk, summary.logged_runs, "{:,.0f}"),
        _reached(summary.seconds_to_walk, summary.logged_runs, None),
        _mean_spread([100 * share for share in summary.wide_walking], "{:.0f}%"),
    ]


def surrogate_rows(summaries: Sequence[SourceSummary]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the surrogate-accuracy table; no rows when no run logged any."""
    names = sorted({name for summary in summaries for name in summary.surrogate})
    rows = [[summary.label, *(_mean_spread(summary.surrogate.get(name, []), "{:.4g}") for name in names)]
            for summary in summaries if summary.surrogate]
    return ["source", *names], rows


def _mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values)


def _mean_spread(values: Sequence[float], number: str) -> str:
    """"mean ± sd" over seeds (the sample sd), the mean alone for one seed, "-" for none."""
    if not values:
        return "-"
    if len(values) == 1:
        return number.format(values[0])
    return f"{number.format(_mean(values))} ± {number.format(float(np.std(values, ddof=1)))}"


def _reached(values: Sequence[float], runs: int, number: str | None) -> str:
    if not runs:
        return "-"
    median = median_to_walk(values, runs)
    if math.isinf(median):
        return f"not reached ({len(values)}/{runs} runs walked)"
    shown = number.format(median) if number else _duration(median)
    return f"{shown} (median; {len(values)}/{runs} runs walked)"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


# -- CSV -------------------------------------------------------------------------------
def write_summary_csv(summaries: Sequence[SourceSummary], path: Path) -> Path:
    """The table's numbers unformatted: mean and sample sd over seeds (sd blank for one seed)."""
    surrogate_names = sorted({name for summary in summaries for name in summary.surrogate})
    rows = []
    for summary in summaries:
        row = {"source": summary.label, "runs": summary.runs, "finished": summary.finished,
               "designs": summary.designs}
        for name in ("mean_reward", "worst_reward", "mean_displacement", "worst_displacement", "walking_designs",
                     "wide_walking"):
            row[name], row[f"{name}_sd"] = _numbers(getattr(summary, name))
        row["runs_walking"] = len(summary.steps_to_walk)
        row["runs_logged"] = summary.logged_runs
        for name, values in (("median_real_steps_to_walk", summary.steps_to_walk),
                             ("median_seconds_to_walk", summary.seconds_to_walk)):
            median = median_to_walk(values, summary.logged_runs)
            row[name] = "" if math.isinf(median) else median  # blank: fewer than half the runs walked
        for name in surrogate_names:
            row[name], row[f"{name}_sd"] = _numbers(summary.surrogate.get(name, []))
        rows.append(row)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]) if rows else ["source"])
        writer.writeheader()
        writer.writerows(rows)
    return path


def _numbers(values: Sequence[float]) -> tuple[float | str, float | str]:
    if not values:
        return "", ""
    return _mean(values), (float(np.std(values, ddof=1)) if len(values) > 1 else "")
