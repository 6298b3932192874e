"""The gym tasks' table: per entry, real env steps to each return level and the return at fixed
budgets, medians over seeds with bootstrap intervals, from the study's records or run folders.

    python study/gym/report.py study/gym/records                       # every entry found
    python study/gym/report.py study/gym/records --task Pendulum-v1 --seeds 0-4
    python study/gym/report.py study/gym/records --seeds 0-4 --figures docs/figures/gym   # and a curve per task

A level is *reached* at the first evaluation whose mean return (the deterministic policy over
``env.evaluation_episodes`` episodes) is at or above it, and *held* at the third of three evaluations
in a row at or above it (credited at the confirming one, as the walker's league credits (b)). A
run that ends before a level is censored at its last evaluation, not failed: the cell then reads
"not by N (cut)" when fewer than half of the seeds reached it. Levels are the task's
(:data:`unipolicy_rl.envs.gym_task.KNOWN_LEVELS`).

With ``--figures DIR``, ``DIR/<task>.png``: each entry's median return over its seeds against real
env steps (log scale: the model-free entries run 10x longer), the band from the lowest to the highest
seed, the levels dotted; a step is drawn while at least half of the entry's seeds reached it.
"""

from __future__ import annotations

import argparse
import math
import random
import sys
from collections import defaultdict
from pathlib import Path

if __package__ in (None, ""):
    sys.path[0] = str(Path(__file__).resolve().parents[2])

from study.records import Record, load  # noqa: E402
from unipolicy_rl.envs.gym_task import KNOWN_LEVELS  # noqa: E402

# Budgets (real env steps) at which each task's table reads the return.
BUDGETS = {"Pendulum": (10_000, 30_000), "InvertedPendulum": (10_000, 30_000), "Hopper": (50_000, 125_000)}
HOLD = 3  # evaluations in a row at or above a level that confirm it is held
BOOTSTRAP = 2000


def task_of(entry: str) -> str:
    """``Pendulum-v1`` of the run name ``Pendulum-v1-moe-trpo``."""
    name, version = entry.split("-")[:2]
    return f"{name}-{version}"


def entry_of(record: Record, task: str) -> str:
    """The row a run belongs to: its folder (the study plan's entry, e.g. ``pendulum-pce-trpo-walker-basis``,
    so two plan entries that share a run name stay apart), less a leading ``<task>-``."""
    folder = record.name.split("/")[0]
    return folder[len(task) + 1:] if folder.startswith(f"{task}-") else folder


def runs_by_entry(records: list[Record], task: str) -> dict[str, list[Record]]:
    """``task``'s runs, grouped by their entry (:func:`entry_of`)."""
    by_entry: dict[str, list[Record]] = defaultdict(list)
    for record in records:
        if task_of(record.entry) == task:
            by_entry[entry_of(record, task)].append(record)
    return by_entry


def steps_to(record: Record, level: float, in_a_row: int) -> tuple[float, bool]:
    """(real env steps, reached): where the run's returns were first ``in_a_row`` evaluations in a
    row at or above ``level`` (credited at the last of them); else (its last evaluation's steps, False)."""
    streak = 0
    for evaluation in record.evaluations:
        streak = streak + 1 if evaluation.mean_return >= level else 0
        if streak >= in_a_row:
            return evaluation.steps, True
    last = record.evaluations[-1].steps if record.evaluations else 0.0
    return last, False


def return_at(record: Record, budget: float) -> float:
    """The return of the run's last evaluation at or before ``budget`` real env steps (NaN if the run
    had not got there)."""
    if not record.evaluations or record.evaluations[-1].steps < budget:
        return math.nan
    before = [e for e in record.evaluations if e.steps <= budget]
    return before[-1].mean_return if before else math.nan


def median(values: list[float]) -> float:
    ordered = sorted(values)
    middle = len(ordered) // 2
    return ordered[middle] if len(ordered) % 2 else (ordered[middle - 1] + ordered[middle]) / 2


def bootstrap(values: list[float], seed: int = 0) -> tuple[float, float]:
    """A 95% percentile bootstrap interval of the median over seeds (``inf``: censored)."""
    generator = random.Random(seed)
    medians = sorted(median([generator.choice(values) for _ in values]) for _ in range(BOOTSTRAP))
    return medians[int(0.025 * BOOTSTRAP)], medians[int(0.975 * BOOTSTRAP) - 1]


def _steps_cell(outcomes: list[tuple[float, bool]]) -> str:
    values = [steps if reached else math.inf for steps, reached in outcomes]
    reached = sum(1 for _, ok in outcomes if ok)
    middle = median(values)
    if math.isinf(middle):
        return f"not by {min(steps for steps, ok in outcomes if not ok):,.0f} (cut; {reached}/{len(outcomes)})"
    low, high = bootstrap(values)
    high_text = "cut" if math.isinf(high) else f"{high:,.0f}"
    return f"{middle:,.0f} [{low:,.0f}, {high_text}] ({reached}/{len(outcomes)})"


def _return_cell(values: list[float]) -> str:
    known = [value for value in values if math.isfinite(value)]
    if not known:
        return "-"
    low, high = bootstrap(known)
    return f"{median(known):.0f} [{low:.0f}, {high:.0f}] ({len(known)})"


def table(records: list[Record], task: str) -> str:
    """The markdown table of ``task``'s entries."""
    prefix = task.split("-")[0]
    levels, budgets = KNOWN_LEVELS.get(prefix, ()), BUDGETS.get(prefix, ())
    by_entry = runs_by_entry(records, task)
    head = ["entry", "seeds"]
    head += [f"reaches {level:g}" for level in levels] + [f"holds {level:g}" for level in levels]
    head += [f"return at {budget:,}" for budget in budgets]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for entry, runs in sorted(by_entry.items()):
        runs.sort(key=lambda record: record.seed)
        row = [entry, ",".join(str(record.seed) for record in runs)]
        row += [_steps_cell([steps_to(record, level, 1) for record in runs]) for level in levels]
        row += [_steps_cell([steps_to(record, level, HOLD) for record in runs]) for level in levels]
        row += [_return_cell([return_at(record, budget) for record in runs]) for budget in budgets]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def curves(records: list[Record], task: str, path: Path) -> Path:
    """The figure of ``task``'s entries (module docstring) at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_entry = runs_by_entry(records, task)
    figure, axes = plt.subplots(figsize=(7, 4.2))
    for entry, runs in sorted(by_entry.items()):
        steps = sorted({e.steps for run in runs for e in run.evaluations})
        drawn = []
        for step in steps:
            values = [v for run in runs if not math.isnan(v := return_at(run, step))]
            if 2 * len(values) >= len(runs):
                drawn.append((step, median(values), min(values), max(values)))
        if not drawn:
            continue
        x, middle, low, high = zip(*drawn, strict=True)
        line, = axes.plot(x, middle, label=f"{entry} ({len(runs)} seeds)")
        axes.fill_between(x, low, high, color=line.get_color(), alpha=0.15)
    for level in KNOWN_LEVELS.get(task.split("-")[0], ()):
        axes.axhline(level, color="grey", linestyle=":", linewidth=1)
    axes.set_xscale("log")
    axes.set_xlabel("real env steps")
    axes.set_ylabel("evaluation return (deterministic policy)")
    axes.set_title(f"{task}: median over seeds, lowest to highest seed shaded")
    axes.legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def parse_seeds(text: str) -> set[int]:
    seeds: set[int] = set()
    for part in text.split(","):
        low, _, high = part.partition("-")
        seeds.update(range(int(low), int(high or low) + 1))
    return seeds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("roots", type=Path, nargs="+", help="record folders or run folders")
    parser.add_argument("--task", default=None, help="one gymnasium id (default: every task found)")
    parser.add_argument("--seeds", type=parse_seeds, default=None, help="e.g. 0-4")
    parser.add_argument("--figures", type=Path, default=None, help="a folder for one curve figure per task")
    args = parser.parse_args(argv)
    records, left_out = load(args.roots)
    records = [record for record in records if record.evaluations and not math.isnan(record.evaluations[0].mean_return)
               and (args.seeds is None or record.seed in args.seeds)]
    tasks = sorted({task_of(record.entry) for record in records}) if args.task is None else [args.task]
    for task in tasks:
        print(f"### {task}\n")
        print(table(records, task))
        print()
        if args.figures is not None:
            print(f"wrote {curves(records, task, args.figures / f'{task}.png')}\n")
    for reason in left_out:
        print(f"left out: {reason}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
