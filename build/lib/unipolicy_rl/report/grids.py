"""Design-grid numbers across seeds: the seed mean per cell and the relative performance.

Relative performance (thesis fig. 6.19) divides a source's reward on a design by the best
reward reachable on that design, because some builds (long light links) simply walk further
than others: it separates "this policy is poor here" from "this robot is slow here". The best
comes from DE policies trained at that very design where the sweep has them (``design=fixed``,
or the DE source at its own design), else from the best any policy of the report reached there.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from unipolicy_rl.evaluation import DesignResult
from unipolicy_rl.report.runs import Run

# Cells are matched by their designs rounded to a micrometre / a milligram per metre, so a
# grid point computed as 0.16250000000000003 is the 0.1625 a config wrote.
DIGITS = 6
Cell = tuple[float, float]


def cell(length: float, density: float) -> Cell:
    return round(float(length), DIGITS), round(float(density), DIGITS)


def cells(results: Iterable[DesignResult], metric: str) -> dict[Cell, float]:
    return {cell(r.length, r.density): float(getattr(r, metric)) for r in results}


@dataclass(frozen=True)
class GridValues:
    """values[density, length] over sorted lengths and densities; NaN where a cell has no value."""

    lengths: np.ndarray
    densities: np.ndarray
    values: np.ndarray

    @classmethod
    def from_cells(cls, by_cell: dict[Cell, float]) -> GridValues:
        lengths = np.array(sorted({length for length, _ in by_cell}))
        densities = np.array(sorted({density for _, density in by_cell}))
        values = np.full((len(densities), len(lengths)), np.nan)
        for (length, density), value in by_cell.items():
            values[np.searchsorted(densities, density), np.searchsorted(lengths, length)] = value
        return cls(lengths, densities, values)

    def worst(self) -> tuple[int, int] | None:
        """(row, column) of the lowest finite cell."""
        if not np.isfinite(self.values).any():
            return None
        row, column = np.unravel_index(np.nanargmin(self.values), self.values.shape)
        return int(row), int(column)


def seed_mean(grids: Sequence[Sequence[DesignResult]], metric: str) -> GridValues:
    """Per cell, the mean over the seeds that evaluated it."""
    collected: dict[Cell, list[float]] = {}
    for results in grids:
        for key, value in cells(results, metric).items():
            collected.setdefault(key, []).append(value)
    return GridValues.from_cells({key: float(np.mean(values)) for key, values in collected.items()})


@dataclass(frozen=True)
class Best:
    """Best episode reward per cell, and the cells whose best comes from a policy trained there."""

    reward: dict[Cell, float]
    trained_there: frozenset[Cell]

    @property
    def mixed(self) -> bool:
        """Some cells' best comes from policies trained there, others' from any policy."""
        return bool(self.trained_there) and not self.trained_there >= set(self.reward)

    @property
    def kind(self) -> str:
        """Where the best came from, in words, for the figure and the report."""
        if self.trained_there and not self.mixed:
            return "best = DE policies trained at each design"
        if self.mixed:
            return (f"best = DE policies trained at the design on {len(self.trained_there)} of "
                    f"{len(self.reward)} designs (marked *), the best policy of any source elsewhere")
        return "best = the best policy of any source on each design (no DE policies trained at the designs)"


def best_achievable(runs: Sequence[Run]) -> Best:
    """Per cell: the best reward of policies trained at that design if any, else of any policy."""
    any_policy: dict[Cell, float] = {}
    trained_there: dict[Cell, float] = {}
    for run in runs:
        if run.designs is None:
            continue
        rewards = cells(run.designs, "mean_episode_reward")
        for key, value in rewards.items():
            any_policy[key] = max(value, any_policy.get(key, -np.inf))
        design = run.design_distribution
        if design is not None and design.is_deterministic:
            home = cell(design.mean.length, design.mean.density)
            if home in rewards:
                trained_there[home] = max(rewards[home], trained_there.get(home, -np.inf))
    return Best({**any_policy, **trained_there}, frozenset(trained_there))


def relative_performance(reward: GridValues, best: Best) -> GridValues:
    """Percent of the best reward per cell; NaN where the best is not positive (a percentage of
    a loss says nothing)."""
    relative = np.full_like(reward.values, np.nan)
    for (row, column), value in np.ndenumerate(reward.values):
        top = best.reward.get(cell(reward.lengths[column], reward.densities[row]), np.nan)
        if np.isfinite(value) and top > 0:
            relative[row, column] = 100.0 * value / top
    return GridValues(reward.lengths, reward.densities, relative)
