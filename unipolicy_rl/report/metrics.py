"""The metrics.csv figures the report reads, and the two axes it compares sources on.

Model-free and model-based training are compared per *real* env step and per second of wall
time, so both axes exist for every run: logged by newer runs (``real_env_steps``,
``time/elapsed``), derived here for older ones. Returns are real ones only: a model-based
run's ``imagined/`` columns (and its rows that log no real episode) are never read as returns.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from unipolicy_rl.evaluation import walks_the_grid
from unipolicy_rl.report.runs import Run
from unipolicy_rl.training.metrics_file import (
    CPU_TIME,
    DISPLACEMENT,
    ELAPSED,
    EPOCH,
    EPOCH_TIMES,
    GRID_MEAN,
    GRID_MIN,
    GRID_WALKING,
    IMAGINED,
    IMAGINED_PREFIX,
    REAL_STEPS,
    REWARD,
)
from unipolicy_rl.training.metrics_file import MODEL_PREFIX as SURROGATE_PREFIX

# The column names are defined with the file's writer (unipolicy_rl.training.metrics_file) and
# re-exported here under the names this module has always offered.
__all__ = [
    "DISPLACEMENT",
    "ELAPSED",
    "EPOCH",
    "EPOCH_TIMES",
    "GRID_MEAN",
    "GRID_MIN",
    "GRID_WALKING",
    "IMAGINED_PREFIX",
    "REAL_STEPS",
    "REWARD",
    "SURROGATE_PREFIX",
    "Series",
    "column",
    "elapsed_seconds",
    "first_walking",
    "median_to_walk",
    "real_env_steps",
    "series",
    "steps_are_derived",
    "surrogate_figures",
    "training_cpu_seconds",
    "training_seconds",
]


@dataclass(frozen=True)
class Series:
    """One run's values of one quantity against both axes."""

    steps: np.ndarray  # real env steps
    seconds: np.ndarray  # wall time
    values: np.ndarray

    def against(self, axis: str) -> tuple[np.ndarray, np.ndarray]:
        return (self.steps if axis == "steps" else self.seconds), self.values


def column(run: Run, name: str) -> np.ndarray:
    return np.array([row.get(name, math.nan) for row in run.rows], dtype=float)


def real_env_steps(run: Run) -> np.ndarray:
    """Per row; a logged column is carried forward over rows that leave it blank. Without
    the column, a real source's epoch trains on ``episodes_per_epoch * episode_length`` steps."""
    if REAL_STEPS in run.columns:
        return _carry_forward(column(run, REAL_STEPS))
    return column(run, EPOCH) * real_steps_per_epoch(run.config)


def real_steps_per_epoch(config: dict) -> int:
    """The real env steps one epoch of a real source trains on, from a run's (resolved) config."""
    return config["episodes_per_epoch"] * config["robot"]["episode_length"]


def elapsed_seconds(run: Run) -> np.ndarray:
    if ELAPSED in run.columns:
        return _carry_forward(column(run, ELAPSED))
    parts = [np.nan_to_num(column(run, name)) for name in EPOCH_TIMES if name in run.columns]
    return np.cumsum(np.sum(parts, axis=0)) if parts else np.full(len(run.rows), math.nan)


def real_rows(run: Run) -> np.ndarray:
    """Per row: whether it is a real epoch's (not an imagined batch's, whose times are parts of it)."""
    return column(run, IMAGINED) != 1.0 if IMAGINED in run.columns else np.ones(len(run.rows), dtype=bool)


def training_seconds(run: Run) -> np.ndarray:
    """Per row: the wall seconds the run spent training up to it, its periodic evaluations and
    checkpoints left out, so that a learner that evaluates more often on its way to a level (the
    schedule is in real env steps) is not charged for it. Each real epoch's row logs how long it
    collected (``time/collect``) and how long everything after took up to its evaluation
    (``time/update``: the policy updates, and a model-based run's fit and imagined updates, whose
    own rows are parts of it and are not added again); every run logs both. A run without them
    falls back to its elapsed time (:func:`elapsed_seconds`)."""
    if not all(name in run.columns for name in EPOCH_TIMES):
        return elapsed_seconds(run)
    real = real_rows(run)
    spent = np.sum([np.nan_to_num(column(run, name)) for name in EPOCH_TIMES], axis=0)
    return np.cumsum(np.where(real, spent, 0.0))


def training_cpu_seconds(run: Run) -> np.ndarray:
    """Per row: the CPU seconds (every core, the worker processes too) the run spent training up
    to it, over the same spans as :func:`training_seconds` (each real epoch's ``time/cpu``); NaN
    from the first real epoch that did not log it on (a run, or its first part before a resume,
    from before the column existed), never a sum with a part missing."""
    if CPU_TIME not in run.columns:
        return np.full(len(run.rows), math.nan)
    real = real_rows(run)
    return np.cumsum(np.where(real, column(run, CPU_TIME), 0.0))


def steps_are_derived(run: Run) -> bool:
    """True when real env steps come from the epoch count, which only holds for real sources."""
    return REAL_STEPS not in run.columns


def series(run: Run, name: str) -> Series | None:
    """``name`` on the rows that log it, against both axes; None when no row does."""
    if name not in run.columns or not run.rows:
        return None
    values = column(run, name)
    logged = np.isfinite(values)
    if not logged.any():
        return None
    return Series(real_env_steps(run)[logged], elapsed_seconds(run)[logged], values[logged])


def first_walking(run: Run) -> tuple[float, float] | None:
    """(real env steps, wall seconds) at the first periodic real-env grid evaluation that walks
    the grid (:func:`~unipolicy_rl.evaluation.walks_the_grid`: mean >= 3 m, every design >= 1 m);
    None if none did or the run logged no periodic evaluation (``evaluation.every=0``)."""
    mean, least = series(run, GRID_MEAN), series(run, GRID_MIN)
    if mean is None or least is None:
        return None
    walking = [i for i, (m, w) in enumerate(zip(mean.values, least.values, strict=True)) if walks_the_grid(m, w)]
    if not walking:
        return None
    return float(mean.steps[walking[0]]), float(mean.seconds[walking[0]])


def median_to_walk(reached: Sequence[float], runs: int) -> float:
    """Median over ``runs`` runs of the figure (steps or seconds) at which those in ``reached``
    walked the grid. A run that did not walk took longer than any that did, so it counts as
    infinitely long: the median is ``inf`` ("not reached") when fewer than half the runs walked,
    instead of a median of the lucky few."""
    if not (isinstance(runs, int) and runs >= len(reached)):
        raise ValueError(f"runs must be an integer >= the {len(reached)} runs that walked, got {runs!r}")
    if runs == 0:
        return math.inf
    return float(np.median([*reached, *[math.inf] * (runs - len(reached))]))


def surrogate_figures(run: Run) -> dict[str, float]:
    """The last logged value of each surrogate-accuracy column."""
    figures = {}
    for name in run.columns:
        if name.startswith(SURROGATE_PREFIX):
            logged = series(run, name)
            if logged is not None:
                figures[name] = float(logged.values[-1])
    return figures


def _carry_forward(values: np.ndarray) -> np.ndarray:
    filled = values.copy()
    for i in range(1, len(filled)):
        if not math.isfinite(filled[i]):
            filled[i] = filled[i - 1]
    return filled
