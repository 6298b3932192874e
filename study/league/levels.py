"""The sample-efficiency league: one protocol for every entry, read from the runs' records.

Every run evaluates on one schedule in real env steps (``evaluation.every_steps``,
``evaluation.dense_until``, ``evaluation.then_every_steps``: every 2,000 up to 100,000, every
10,000 after), the deterministic policy on the 5 x 5 design grid in the real env, one episode per
design. From those evaluations, per run:

- ``first_walk`` (a): the first evaluation that walks the grid: grid mean >= 3 m and every
  design >= 1 m (:func:`~unipolicy_rl.evaluation.walks_the_grid`).
- ``stays_walking`` (b): the evaluation that completes the first streak of :data:`STREAK` (3)
  consecutive evaluations that walk the grid: the level is credited at the streak's *third*,
  confirming evaluation, when a user watching the run could say it stays walking. A run that
  walks once and falls back does not reach it there.
- ``se_trpo_final`` (c): the first evaluation at SE-TRPO's final level: grid mean >=
  :data:`SE_TRPO_FINAL_MEAN` (5 m) and every design >= :data:`SE_TRPO_FINAL_MIN` (2.5 m).
- (d) the grid mean and worst design at the first evaluation at or after each of
  :data:`MILESTONES` (50,000, 100,000 and 300,000 real env steps); None where the run did not
  get there.

An entry is a run name (``run_name``: ``se-trpo``, ``se-moe-trpo``), its runs the seeds;
model-free entries are those whose config says ``source.kind: real``. Per entry and level: how
many runs reached it, the median real env steps (and wall and CPU seconds) with a run that never
reached it counting as longer than any that did (``inf``), a percentile-bootstrap 95% interval
of that median (runs resampled with replacement, seeded; a bound may be ``inf``: "not
reached"), and how many times fewer real env steps it took than SE-TRPO and than the best
model-free entry (the one with the smallest median at that level). A run cut before its budget
(stopped, or still going) that has not reached a level is censored there, not a failure: beside
the median the table prints what it is already known to be at least, each cut run counted at the
earliest it could still reach the level, and a median the cut runs leave open reads "not reached
by N (cut)": N real env steps were not enough, more were not tried.

Seconds compare only between runs on one machine at one load: a record names its machine
(``machine``, a label given when it was written), and the table shows seconds only where every run
in it carries the same label.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from study.records import Evaluation, Record
from unipolicy_rl.evaluation import GRID_WALKING_MEAN, WALKING_DISPLACEMENT, walks_the_grid

# SE-TRPO's final level (c): the grid mean and the worst design its final policies reach (m).
SE_TRPO_FINAL_MEAN = 5.0
SE_TRPO_FINAL_MIN = 2.5
# Consecutive walking evaluations that make a run "stay walking" (b).
STREAK = 3
# Real env steps at which the grid is read (d): the first evaluation at or after each.
MILESTONES = (50_000, 100_000, 300_000)
# What every entry is compared with.
BASELINE = "se-trpo"
# The bootstrap of the median: resamples, seed, and the interval's coverage.
RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95


def reaches_se_trpo_final(grid_mean: float, grid_min: float) -> bool:
    """Grid mean >= :data:`SE_TRPO_FINAL_MEAN` m with every design >= :data:`SE_TRPO_FINAL_MIN` m."""
    return grid_mean >= SE_TRPO_FINAL_MEAN and grid_min >= SE_TRPO_FINAL_MIN


def first_walk(evaluations: Sequence[Evaluation]) -> Evaluation | None:
    """(a) The first evaluation that walks the grid (mean >= 3 m, every design >= 1 m)."""
    return next((e for e in evaluations if walks_the_grid(e.grid_mean, e.grid_min)), None)


def stays_walking(evaluations: Sequence[Evaluation], streak: int = STREAK) -> Evaluation | None:
    """(b) The evaluation that completes the first ``streak`` consecutive evaluations that all walk
    the grid: the level is credited there (its steps and wall time), when the streak is confirmed,
    not at its first evaluation. None while no such streak is complete."""
    run = 0
    for e in evaluations:
        run = run + 1 if walks_the_grid(e.grid_mean, e.grid_min) else 0
        if run == streak:
            return e
    return None


def se_trpo_final(evaluations: Sequence[Evaluation]) -> Evaluation | None:
    """(c) The first evaluation at SE-TRPO's final level (mean >= 5 m, every design >= 2.5 m)."""
    return next((e for e in evaluations if reaches_se_trpo_final(e.grid_mean, e.grid_min)), None)


def at_milestone(evaluations: Sequence[Evaluation], steps: float) -> Evaluation | None:
    """(d) The first evaluation at or after ``steps`` real env steps; None if the run did not get there."""
    return next((e for e in evaluations if e.steps >= steps), None)


def earliest_still_possible(evaluations: Sequence[Evaluation], key: str) -> float:
    """The fewest real env steps at which a run cut before its budget, that has not reached level
    ``key``, could still have been found to reach it: its last evaluation's (every level, (b)
    included, is credited at an evaluation, and the next comes later); 0 before its first
    evaluation. A lower bound, never a guess."""
    return evaluations[-1].steps if evaluations else 0.0


@dataclass(frozen=True)
class Level:
    key: str
    label: str  # (a), (b), (c)
    description: str
    find: Callable[[Sequence[Evaluation]], Evaluation | None]


LEVELS = (
    Level("first_walk", "(a)", f"first walks the grid: grid mean >= {GRID_WALKING_MEAN:g} m and every design >= "
          f"{WALKING_DISPLACEMENT:g} m", first_walk),
    Level("stays_walking", "(b)", f"walks and stays walking: credited at the last of {STREAK} consecutive "
          f"evaluations that walk the grid", stays_walking),
    Level("se_trpo_final", "(c)", f"SE-TRPO's final level: grid mean >= {SE_TRPO_FINAL_MEAN:g} m and every design "
          f">= {SE_TRPO_FINAL_MIN:g} m", se_trpo_final),
)


# -- one run ---------------------------------------------------------------------------
@dataclass(frozen=True)
class RunResult:
    """One run's evaluations, the evaluation at which it reached each level, and the (d) figures."""

    name: str
    entry: str
    seed: int | None
    model_free: bool
    step_schedule: bool
    evaluations: tuple[Evaluation, ...]
    levels: dict[str, Evaluation | None]
    milestones: dict[int, Evaluation | None]
    # Trained to its budget (its final evaluation exists). A run cut before it (stopped, or still
    # going) that has not reached a level is censored there: the table counts it apart ("cut"), not
    # as never reaching it.
    finished: bool = True
    machine: str | None = None  # runs with one label ran on one machine at one load (their seconds compare)
    fit: str = "-"  # the model fit's precision and threads, as the record names them ("-": no model)


def run_result(record: Record) -> RunResult:
    found = record.evaluations
    return RunResult(name=record.name, entry=record.entry, seed=record.seed, model_free=record.model_free,
                     step_schedule=record.step_schedule, evaluations=tuple(found),
                     levels={level.key: level.find(found) for level in LEVELS},
                     milestones={steps: at_milestone(found, steps) for steps in MILESTONES}, finished=record.finished,
                     machine=record.machine, fit=fit_settings(record))


def fit_settings(record: Record) -> str:
    """What the model's fits ran in: ``bfloat16, 2 threads``; ``-`` for a run without a model."""
    if record.model_free:
        return "-"
    if record.precision is None:
        return "not recorded"  # a run from before the setting, or a model fitted in closed form
    # null: the trainer keeps the run's own thread count (train.py runs on one thread).
    threads = "the run's one thread" if record.threads is None else f"{record.threads} threads"
    return f"{record.precision}, {threads}"


def one_machine(runs: Sequence[RunResult]) -> str | None:
    """The machine label every run shares (their seconds compare), or None."""
    labels = {run.machine for run in runs}
    return labels.pop() if len(labels) == 1 and None not in labels else None


# -- statistics ------------------------------------------------------------------------
def median(values: Sequence[float]) -> float:
    """The median, ``inf`` allowed (a run that never reached a level); ``inf`` when empty."""
    return float(np.median(np.asarray(values, dtype=float))) if len(values) else math.inf


def bootstrap_interval(values: Sequence[float], resamples: int = RESAMPLES, seed: int = BOOTSTRAP_SEED,
                       confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Percentile-bootstrap interval of the median of ``values`` (``inf`` allowed): the runs
    resampled with replacement ``resamples`` times from ``seed``. Order statistics of the
    resampled medians, never an interpolation between them (one between a finite median and
    ``inf`` would be meaningless). ``(inf, inf)`` when empty."""
    data = np.asarray(values, dtype=float)
    if not len(data):
        return math.inf, math.inf
    draws = np.random.default_rng(seed).integers(0, len(data), size=(resamples, len(data)))
    medians = np.sort(np.median(data[draws], axis=1))
    tail = (1.0 - confidence) / 2.0
    low = int(math.floor(tail * resamples))
    high = int(math.ceil((1.0 - tail) * resamples)) - 1
    return float(medians[low]), float(medians[high])


def fewer(reference: float, value: float) -> float:
    """How many times fewer real env steps ``value`` took than ``reference``: ``reference / value``;
    ``inf`` when only the reference never reached the level, 0 when only ``value`` did not, NaN
    when neither did."""
    if math.isinf(reference) and math.isinf(value):
        return math.nan
    if value == 0:
        return math.inf
    return reference / value


@dataclass(frozen=True)
class LevelStats:
    reached: int  # runs that reached the level
    runs: int
    steps: float  # median real env steps (inf: not reached by half the runs)
    steps_interval: tuple[float, float]  # bootstrap 95% interval of that median
    seconds: float  # median wall seconds
    seconds_interval: tuple[float, float]
    unfinished: int = 0  # runs that have not reached the level but have not trained to their budget either
    cpu_seconds: float = math.nan  # median CPU seconds; NaN when a run that reached the level did not log them
    # What the median is already known to be at least, however the unfinished runs go on: each at
    # the earliest it could still reach the level (:func:`earliest_still_possible`). = steps when
    # no run is unfinished; what decides a comparison before the last runs end.
    steps_at_least: float = math.nan


@dataclass
class Entry:
    name: str
    model_free: bool
    runs: list[RunResult]
    levels: dict[str, LevelStats] = field(default_factory=dict)
    # steps -> (median grid mean, median worst design, runs that got there), over those runs
    milestones: dict[int, tuple[float, float, int]] = field(default_factory=dict)

    @property
    def seeds(self) -> list:
        return sorted((run.seed for run in self.runs), key=lambda seed: (seed is None, seed))


def level_stats(runs: Sequence[RunResult], key: str, resamples: int = RESAMPLES,
                seed: int = BOOTSTRAP_SEED) -> LevelStats:
    """One level over an entry's runs; a run that has not reached it counts as ``inf`` (so while a
    run is still going, the median and interval are provisional: ``unfinished`` counts those runs)."""
    found = [run.levels[key] for run in runs]
    steps = [e.steps if e is not None else math.inf for e in found]
    at_least = [earliest_still_possible(run.evaluations, key) if e is None and not run.finished else value
                for e, run, value in zip(found, runs, steps, strict=True)]
    seconds = [e.seconds if e is not None else math.inf for e in found]
    cpu = [e.cpu_seconds if e is not None else math.inf for e in found]
    return LevelStats(reached=sum(e is not None for e in found), runs=len(found),
                      steps=median(steps), steps_interval=bootstrap_interval(steps, resamples, seed),
                      seconds=median(seconds), seconds_interval=bootstrap_interval(seconds, resamples, seed),
                      unfinished=sum(e is None and not run.finished for e, run in zip(found, runs, strict=True)),
                      cpu_seconds=math.nan if any(math.isnan(value) for value in cpu) else median(cpu),
                      steps_at_least=median(at_least))


def make_entries(results: Sequence[RunResult], resamples: int = RESAMPLES, seed: int = BOOTSTRAP_SEED) -> list[Entry]:
    """The runs grouped by run name; SE-TRPO first, then model-free entries, then the rest, by name."""
    by_name: dict[str, list[RunResult]] = {}
    for result in results:
        by_name.setdefault(result.entry, []).append(result)
    entries = []
    for name, runs in by_name.items():
        entry = Entry(name, all(run.model_free for run in runs), runs)
        entry.levels = {level.key: level_stats(runs, level.key, resamples, seed) for level in LEVELS}
        for steps in MILESTONES:
            there = [run.milestones[steps] for run in runs if run.milestones[steps] is not None]
            if there:
                entry.milestones[steps] = (median([e.grid_mean for e in there]),
                                           median([e.grid_min for e in there]), len(there))
        entries.append(entry)
    return sorted(entries, key=lambda e: (e.name != BASELINE, not e.model_free, e.name))


def best_model_free(entries: Sequence[Entry], key: str) -> Entry | None:
    """The model-free entry with the smallest median real env steps at level ``key`` (the first
    by name among equals); None when there is no model-free entry or none reached the level."""
    candidates = [entry for entry in entries if entry.model_free and math.isfinite(entry.levels[key].steps)]
    return min(candidates, key=lambda entry: (entry.levels[key].steps, entry.name)) if candidates else None


def baseline_entry(entries: Sequence[Entry], name: str = BASELINE) -> Entry | None:
    return next((entry for entry in entries if entry.name == name), None)


# -- the table -------------------------------------------------------------------------
def format_count(value: float, unit: str = "") -> str:
    if math.isnan(value):
        return "-"
    return "not reached" if math.isinf(value) else f"{value:,.0f}{unit}"


def format_interval(interval: tuple[float, float]) -> str:
    return f"[{format_count(interval[0])}, {format_count(interval[1])}]"


def format_fewer(ratio: float) -> str:
    if math.isnan(ratio):
        return "-"
    if ratio == 0:
        return "not reached"
    if math.isinf(ratio):
        return "only this reached"
    return f"{ratio:.1f}x fewer"


def ratio_lines(entries: Sequence[Entry], key: str, baseline: str = BASELINE) -> dict[str, tuple[str, str]]:
    """Entry name -> (vs the baseline, vs the best model-free entry) at level ``key``, as printed."""
    reference = baseline_entry(entries, baseline)
    best = best_model_free(entries, key)
    lines = {}
    for entry in entries:
        stats = entry.levels[key]
        steps = stats.steps
        if math.isinf(steps) and stats.unfinished and math.isfinite(stats.steps_at_least):
            lines[entry.name] = ("- (cut)", "- (cut)")  # censored: not a failure to compare
            continue
        versus_baseline = format_fewer(fewer(reference.levels[key].steps, steps)) if reference else "no runs"
        versus_best = format_fewer(fewer(best.levels[key].steps, steps)) if best else "none reached"
        lines[entry.name] = (versus_baseline, versus_best)
    return lines


def format_league(entries: Sequence[Entry], baseline: str = BASELINE) -> str:
    """The league as printed: the entries and their seeds, then per level reached k/n, the
    median real env steps [95% interval], the median wall time, and the two ratios; then the
    grid at each milestone."""
    width = max([len("entry"), *(len(entry.name) for entry in entries)])
    machine = one_machine([run for entry in entries for run in entry.runs])
    lines = [f"{'entry':<{width}}  {'kind':<11} {'runs':>4}  {'seeds':<24} model fit"]
    for entry in entries:
        kind = "model-free" if entry.model_free else "model-based"
        fits = "; ".join(sorted({run.fit for run in entry.runs}))
        lines.append(f"{entry.name:<{width}}  {kind:<11} {len(entry.runs):>4}  "
                     f"{', '.join(str(seed) for seed in entry.seeds):<24} {fits}".rstrip())
    for level in LEVELS:
        best = best_model_free(entries, level.key)
        ratios = ratio_lines(entries, level.key, baseline)
        rows = []
        for entry in entries:
            stats = entry.levels[level.key]
            steps = format_median(stats)
            unfinished = f" ({stats.unfinished} cut)" if stats.unfinished else ""
            rows.append((entry.name, f"{stats.reached}/{stats.runs}{unfinished}", steps, stats))
        reached_width = max([18, *(len(row[1]) for row in rows)])
        steps_width = max([44, *(len(row[2]) + 1 for row in rows)])
        lines += ["", f"{level.label} {level.key}: {level.description}",
                  f"{'entry':<{width}}  {'reached':>{reached_width}}  {'median real steps [95% CI]':<{steps_width}} "
                  f"{'median wall s':>13} {'median CPU s':>12}  "
                  f"{'vs ' + baseline:<17} vs best model-free ({best.name if best else 'none reached'})"]
        for name, reached, steps, stats in rows:
            wall, cpu = ((format_count(stats.seconds), format_count(stats.cpu_seconds)) if machine else ("-", "-"))
            lines.append(f"{name:<{width}}  {reached:>{reached_width}}  {steps:<{steps_width}} "
                         f"{wall:>13} {cpu:>12}  {ratios[name][0]:<17} {ratios[name][1]}")
    lines += ["", "(d) the grid at the first evaluation at or after each milestone: median grid mean / median worst "
              "design (m), over the runs that got there"]
    lines.append((f"{'entry':<{width}}  " + "  ".join(f"{f'{steps:,} steps':<22}" for steps in MILESTONES)).rstrip())
    for entry in entries:
        cells = []
        for steps in MILESTONES:
            if steps in entry.milestones:
                mean, worst, there = entry.milestones[steps]
                cells.append(f"{mean:.2f} / {worst:.2f} ({there}/{len(entry.runs)})")
            else:
                cells.append(f"- (0/{len(entry.runs)})")
        lines.append((f"{entry.name:<{width}}  " + "  ".join(f"{cell:<22}" for cell in cells)).rstrip())
    seconds = (f"all runs on one machine at one load ({machine})" if machine else
               "'-': the runs did not all run on one machine at one load (their records name no common machine), "
               "so their seconds do not compare")
    lines += ["", "(k cut): runs stopped before their budget that had not reached the level: censored, not failures; "
              "(>= N with the cut runs): the median is at least N however they would have gone on (each counted at "
              "its last evaluation); not reached by N (cut): the cut runs leave the median open past N real env steps",
              "median wall s: wall seconds spent training (collecting, fitting, updating), the periodic "
              "evaluations and checkpoints left out; median CPU s: the CPU seconds of the same spans, every core "
              "and the collector's worker processes counted (time/cpu; '-' where a run from before it did not "
              f"log them); seconds: {seconds}"]
    return "\n".join(lines)


def format_median(stats: LevelStats) -> str:
    """A level's median real env steps [95% interval], with what the cut runs leave open."""
    if math.isinf(stats.steps) and stats.unfinished and math.isfinite(stats.steps_at_least):
        return f"not reached by {format_count(stats.steps_at_least)} (cut)"
    text = f"{format_count(stats.steps)} {format_interval(stats.steps_interval)}"
    if stats.unfinished and stats.steps_at_least != stats.steps:
        text += f" (>= {format_count(stats.steps_at_least)} with the cut runs)"
    return text


def cpu_note(evaluation: Evaluation) -> str:
    """``, N CPU s`` where the run logged its CPU seconds, else nothing."""
    return "" if math.isnan(evaluation.cpu_seconds) else f", {evaluation.cpu_seconds:,.0f} CPU s"


def reached_at(evaluation: Evaluation | None, timed: bool) -> str:
    """A run's real env steps at a level, and its seconds there where they compare (``timed``)."""
    if evaluation is None:
        return "-"
    seconds = f" ({evaluation.seconds:,.0f} s{cpu_note(evaluation)})" if timed else ""
    return f"{format_count(evaluation.steps)}{seconds}"


def format_runs(results: Sequence[RunResult]) -> str:
    """Each run: its entry, seed, and the real env steps (and training seconds) at which it reached each level.

    Seconds are shown for runs whose record names their machine (:func:`one_machine`): compare them
    between runs with the same label only."""
    width = max([len("run"), *(len(result.name) for result in results)])
    lines = [f"{'run':<{width}}  {'entry':<16} " + " ".join(f"{level.label + ' ' + level.key:>22}" for level in LEVELS)
             + f" {'evaluations':>11} {'last at':>9}  status"]
    for result in results:
        timed = result.machine is not None
        reached = " ".join(f"{reached_at(e, timed):>22}" for e in result.levels.values())
        last = f"{result.evaluations[-1].steps:,.0f}" if result.evaluations else "-"
        note = "" if result.step_schedule else "  (evaluated every evaluation.every epochs: an older run)"
        status = "done" if result.finished else "cut"
        lines.append(f"{result.name:<{width}}  {result.entry:<16} {reached} {len(result.evaluations):>11} "
                     f"{last:>9}  {status}{note}")
    return "\n".join(lines)


def write_csv(entries: Sequence[Entry], path: Path, baseline: str = BASELINE) -> Path:
    """One row per entry and level: the table's numbers, unformatted (``inf``: not reached)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["entry", "model_free", "runs", "level", "reached", "unfinished", "median_steps", "steps_low",
                         "steps_high", "median_steps_at_least", "median_seconds", "seconds_low", "seconds_high",
                         "median_cpu_seconds", f"fewer_than_{baseline}",
                         "best_model_free", "fewer_than_best_model_free"])
        reference = baseline_entry(entries, baseline)
        timed = one_machine([run for entry in entries for run in entry.runs]) is not None
        for level in LEVELS:
            best = best_model_free(entries, level.key)
            for entry in entries:
                stats = entry.levels[level.key]
                seconds = ([stats.seconds, *stats.seconds_interval, stats.cpu_seconds] if timed else ["", "", "", ""])
                writer.writerow([entry.name, entry.model_free, stats.runs, level.key, stats.reached, stats.unfinished,
                                 stats.steps, *stats.steps_interval, stats.steps_at_least, *seconds,
                                 fewer(reference.levels[level.key].steps, stats.steps) if reference else "",
                                 best.name if best else "", fewer(best.levels[level.key].steps, stats.steps)
                                 if best else ""])
    return path


# -- the figure ------------------------------------------------------------------------
def seed_curves(runs: Sequence[RunResult], value: Callable[[Evaluation], float]) -> tuple[np.ndarray, ...]:
    """(x, median, low, high) over the seeds: at each real env step any seed evaluated at, each
    seed's latest evaluation at or before it, for the seeds whose evaluations span it; the band
    is the seeds' minimum to maximum."""
    curves = [(np.array([e.steps for e in run.evaluations]), np.array([value(e) for e in run.evaluations]))
              for run in runs if run.evaluations]
    if not curves:
        return (np.array([]),) * 4
    x = np.unique(np.concatenate([steps for steps, _ in curves]))
    values = np.full((len(curves), len(x)), np.nan)
    for i, (steps, ys) in enumerate(curves):
        inside = (x >= steps[0]) & (x <= steps[-1])
        values[i, inside] = ys[np.searchsorted(steps, x[inside], side="right") - 1]
    return x, np.nanmedian(values, axis=0), np.nanmin(values, axis=0), np.nanmax(values, axis=0)


LINE_STYLES = ("-", "--", "-.", ":")


def line_style(index: int) -> tuple[tuple, str]:
    """Entry ``index``'s colour and line style: the ten colours of tab10, then the same colours
    dashed, and so on, so no two of up to 40 entries look alike."""
    from matplotlib import colormaps

    return colormaps["tab10"](index % 10), LINE_STYLES[(index // 10) % len(LINE_STYLES)]


def plot_league(entries: Sequence[Entry], path: Path) -> Path:
    """Two panels against real env steps (log axis): grid mean and worst design, one line (the
    median over seeds) and one band (min to max over seeds) per entry, the levels' thresholds dotted."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(12, 4.8), dpi=120, layout="constrained")
    panels = figure.subplots(1, 2, sharex=True)
    for axes, value, label, thresholds in (
        (panels[0], lambda e: e.grid_mean, "grid mean displacement (m)", (GRID_WALKING_MEAN, SE_TRPO_FINAL_MEAN)),
        (panels[1], lambda e: e.grid_min, "worst design's displacement (m)", (WALKING_DISPLACEMENT, SE_TRPO_FINAL_MIN)),
    ):
        for i, entry in enumerate(entries):
            x, middle, low, high = seed_curves(entry.runs, value)
            if not len(x):
                continue
            colour, style = line_style(i)
            seeds = f"{len(entry.runs)} seed{'s' if len(entry.runs) != 1 else ''}"
            axes.plot(x, middle, color=colour, linestyle=style, label=f"{entry.name} ({seeds})")
            axes.fill_between(x, low, high, color=colour, alpha=0.2, linewidth=0)
        for threshold in thresholds:
            axes.axhline(threshold, color="grey", linestyle=":", linewidth=1)
        axes.set_xscale("log")
        axes.set_xlabel("real env steps")
        axes.set_ylabel(label)
        axes.grid(True, which="both", alpha=0.3)
    panels[0].set_title("design grid, deterministic policy: median over seeds, band min-max")
    panels[0].legend(fontsize="small")
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    return path
