"""Holding the level: whether a policy stays where it got, and what the policy a user keeps is worth.

The league's levels say when a run *first* gets somewhere; a user keeps the policy at the end of
training. Per entry, from the same periodic evaluations:

- the share of evaluations at or above each level after the run first reached it (the evaluations
  after the one that reached it, pooled over the entry's runs): for (a) and (b) the share that
  walk the grid, for (c) the share at SE-TRPO's final level; and the lowest worst design among them;
- the policy at a fixed budget (the first evaluation at or after it: the policy training had then,
  not the best one seen): :data:`MODEL_BASED_BUDGETS` for model-based entries,
  :data:`MODEL_FREE_BUDGET` for model-free ones; its median grid mean and worst design, and how many
  runs are at or above SE-TRPO's final median (the median grid mean and median worst design of the
  baseline's runs at :data:`MODEL_FREE_BUDGET`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from study.league.levels import BASELINE, LEVELS, Entry, RunResult, at_milestone, median, reaches_se_trpo_final
from study.records import Evaluation
from unipolicy_rl.evaluation import walks_the_grid

MODEL_BASED_BUDGETS = (50_000, 100_000)  # real env steps: a sixth of SE-TRPO's and less
MODEL_FREE_BUDGET = 600_000  # SE-TRPO's budget
# What "at or above" a level means for an evaluation after it: (a) and (b) walk the grid, (c) is at (c).
HOLDS: dict[str, Callable[[Evaluation], bool]] = {
    "first_walk": lambda e: walks_the_grid(e.grid_mean, e.grid_min),
    "stays_walking": lambda e: walks_the_grid(e.grid_mean, e.grid_min),
    "se_trpo_final": lambda e: reaches_se_trpo_final(e.grid_mean, e.grid_min),
}


@dataclass(frozen=True)
class Holding:
    """One entry at one level: the evaluations after the runs reached it."""

    held: int  # evaluations at or above the level after it was first reached
    after: int  # evaluations after it was first reached
    runs: int  # runs that reached it and evaluated after
    lowest: Evaluation | None  # the evaluation with the lowest worst design among them

    @property
    def share(self) -> float:
        return self.held / self.after if self.after else math.nan


def holding(runs: Sequence[RunResult], key: str) -> Holding:
    """Pooled over ``runs``: the evaluations after each run first reached level ``key``."""
    held = after = reached = 0
    lowest = None
    for run in runs:
        found = run.levels[key]
        if found is None:
            continue
        later = [e for e in run.evaluations if e.steps > found.steps]
        if not later:
            continue
        reached += 1
        after += len(later)
        held += sum(HOLDS[key](e) for e in later)
        worst = min(later, key=lambda e: e.grid_min)
        if lowest is None or worst.grid_min < lowest.grid_min:
            lowest = worst
    return Holding(held, after, reached, lowest)


@dataclass(frozen=True)
class AtBudget:
    """An entry's policies at a fixed budget of real env steps."""

    steps: int
    grid_mean: float  # median over the runs that got there (m)
    grid_min: float  # median worst design (m)
    there: int  # runs that got there
    runs: int
    at_target: int  # of those, runs at or above the target (both figures)


def budgets(entry: Entry) -> tuple[int, ...]:
    return (MODEL_FREE_BUDGET,) if entry.model_free else MODEL_BASED_BUDGETS


def target(entries: Sequence[Entry], baseline: str = BASELINE) -> tuple[float, float] | None:
    """SE-TRPO's final median: the median grid mean and median worst design of the baseline's runs
    at :data:`MODEL_FREE_BUDGET`; None without a baseline run that got there."""
    entry = next((entry for entry in entries if entry.name == baseline), None)
    finals = [e for run in (entry.runs if entry else []) if (e := at_milestone(run.evaluations, MODEL_FREE_BUDGET))]
    if not finals:
        return None
    return median([e.grid_mean for e in finals]), median([e.grid_min for e in finals])


def at_budget(entry: Entry, steps: int, goal: tuple[float, float] | None) -> AtBudget:
    there = [e for run in entry.runs if (e := at_milestone(run.evaluations, steps))]
    at_target = sum(e.grid_mean >= goal[0] and e.grid_min >= goal[1] for e in there) if goal else 0
    return AtBudget(steps, median([e.grid_mean for e in there]) if there else math.nan,
                    median([e.grid_min for e in there]) if there else math.nan, len(there), len(entry.runs), at_target)


def format_holding(entries: Sequence[Entry], baseline: str = BASELINE) -> str:
    """(e) the shares after each level and the lowest worst design after (c); (f) the policy at a budget."""
    width = max([len("entry"), *(len(entry.name) for entry in entries)])
    lines = ["(e) holding the level: evaluations at or above each level after first reaching it, pooled over the "
             "runs ((a), (b): walks the grid; (c): at (c)); lowest worst design after (b) (m, at real env steps)",
             f"{'entry':<{width}}  " + "  ".join(f"{level.label + ' after ' + level.label:<20}" for level in LEVELS)
             + "  lowest worst design after (b)"]
    for entry in entries:
        cells = []
        for level in LEVELS:
            found = holding(entry.runs, level.key)
            cells.append(f"{found.held}/{found.after} ({100 * found.share:.0f}%)" if found.after else "-")
        lowest = holding(entry.runs, "stays_walking").lowest
        worst = f"{lowest.grid_min:.2f} at {lowest.steps:,.0f}" if lowest else "-"
        lines.append(f"{entry.name:<{width}}  " + "  ".join(f"{cell:<20}" for cell in cells) + f"  {worst}")
    goal = target(entries, baseline)
    goal_text = f"{goal[0]:.2f} m / {goal[1]:.2f} m" if goal else "none: no baseline run got there"
    lines += ["", f"(f) the policy at a fixed budget (the first evaluation at or after it, not the best one seen): "
              f"median grid mean / median worst design (m) (runs there); runs at or above {baseline}'s final "
              f"median ({goal_text}, at {MODEL_FREE_BUDGET:,})",
              f"{'entry':<{width}}  {'budget':>9}  {'grid mean / worst':<24} at or above"]
    for entry in entries:
        for steps in budgets(entry):
            found = at_budget(entry, steps, goal)
            figures = (f"{found.grid_mean:.2f} / {found.grid_min:.2f} ({found.there}/{found.runs})" if found.there
                       else f"- (0/{found.runs})")
            reached = f"{found.at_target}/{found.there}" if goal and found.there else "-"
            lines.append(f"{entry.name:<{width}}  {steps:>9,}  {figures:<24} {reached}")
    return "\n".join(lines)
