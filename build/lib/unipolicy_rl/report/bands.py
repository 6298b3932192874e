"""Mean and 95% confidence band across seeds of curves that were logged at different x.

Seeds of a model-based run reach a given number of real env steps at different rows, and
no two seeds take the same wall time, so each seed is interpolated onto one shared x grid,
and only inside its own logged range: a seed that stopped early (a crashed job, a running
one) counts where it has data and nowhere else, so the band says how many seeds it rests on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Student's t, two-sided 95% (the 0.975 quantile), by degrees of freedom: with a handful of
# seeds the normal 1.96 would draw the band far too narrow. Beyond 30 the normal is within 4%.
T_975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145,
         2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048,
         2.045, 2.042)
NORMAL_975 = 1.960
MAX_POINTS = 300


def t_quantile(degrees_of_freedom: int) -> float:
    if degrees_of_freedom < 1:
        raise ValueError(f"a confidence band needs at least 2 seeds, got {degrees_of_freedom + 1}")
    return T_975[degrees_of_freedom - 1] if degrees_of_freedom <= len(T_975) else NORMAL_975


@dataclass(frozen=True)
class Band:
    """Across-seed mean, 95% confidence interval of the mean (NaN where one seed) and seed count."""

    x: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    seeds: np.ndarray  # how many seeds cover each x


def seed_band(curves: Sequence[tuple[np.ndarray, np.ndarray]], max_points: int = MAX_POINTS) -> Band | None:
    """``curves`` is one (x, y) per seed, x increasing; None when no seed has a finite point."""
    cleaned = []
    for x, y in curves:
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        finite = np.isfinite(x) & np.isfinite(y)
        if finite.any():
            order = np.argsort(x[finite], kind="stable")
            cleaned.append((x[finite][order], y[finite][order]))
    if not cleaned:
        return None
    # The seeds' own x when they are few (real sources log every seed at the same steps).
    grid = np.unique(np.concatenate([x for x, _ in cleaned]))
    if len(grid) > max_points:
        grid = np.linspace(grid[0], grid[-1], max_points)
    values = np.full((len(cleaned), len(grid)), np.nan)
    for i, (x, y) in enumerate(cleaned):
        inside = (grid >= x[0]) & (grid <= x[-1])
        values[i, inside] = np.interp(grid[inside], x, y)
    seeds = np.isfinite(values).sum(0)
    mean = np.nanmean(values, 0)
    half = np.full(len(grid), np.nan)
    several = seeds >= 2
    if several.any():
        spread = np.nanstd(values[:, several], 0, ddof=1)
        quantiles = np.array([t_quantile(int(n) - 1) for n in seeds[several]])
        half[several] = quantiles * spread / np.sqrt(seeds[several])
    return Band(grid, mean, mean - half, mean + half, seeds)
