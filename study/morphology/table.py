"""One policy for many robots against a specialist per robot: the table of issue 23, from run records.

A *specialist* run trains on one morphology of the grammar's split (``robot.specialist``) on
real data; a *universal* run on the first ``robot.training_morphologies`` of its training side
(all of them when unset). A run on a world model's data (``source=moe``) is an entry of its own,
cut to one robot or not, measured against the same specialists (what a world model is worth on
the grammar's robots, beside what it costs in real env steps). A grammar run's record
(:mod:`study.records`, written by :mod:`study.morphology.grammar_runs`) holds its final
evaluation per morphology (the deterministic policy on the ``evaluation.grid`` design grid) and
each robot's side of the split, which is all this module reads. Morphologies are matched by their
derivation, so a specialist and a universal policy are compared on the same robot whatever its
index on either side.

Per universal entry (its policy and how many morphologies it trained on) and morphology: the
universal policy's grid mean displacement over the specialist's (the median over specialist
seeds, when there are several). Then per entry: the median of that ratio over the morphologies
it trained on and over the held-out ones (zero-shot), how many of its training
morphologies it walks (grid mean >= ``WALKS`` m), and the real env steps it took: its own, and a
distilled run's teachers' beside them (the issue's budget is the specialists' steps together).
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from study.morphology.grammar_runs import HELD_OUT, TRAINED, UNTRAINED
from study.records import Record

WALKS = 1.0  # m of grid mean displacement: a morphology the policy walks


@dataclass(frozen=True)
class MorphologyScore:
    """One morphology's final evaluation in one run (a row of ``evaluation/morphologies.csv``)."""

    derivation: str
    links: int
    mean_displacement: float
    worst_displacement: float


@dataclass(frozen=True)
class Comparison:
    """A universal entry against the specialists on one morphology."""

    entry: str
    derivation: str
    side: str
    links: int
    universal: float
    specialist: float | None  # the specialists' median grid mean; None when no specialist ran on it
    real_steps: float = math.nan     # the run's own real env steps at its final evaluation
    teacher_steps: float = math.nan  # a distilled run's teachers' real env steps together; NaN for others
    run: str = ""                    # the run it comes from (its name under the report's roots)

    @property
    def ratio(self) -> float:
        """universal / specialist grid mean; NaN without a specialist or where it does not move forward."""
        if self.specialist is None or not self.specialist > 0:
            return math.nan
        return self.universal / self.specialist


@dataclass(frozen=True)
class EntrySummary:
    entry: str
    trained_ratio: float      # median over trained morphologies with a specialist
    held_out_ratio: float     # median over held-out morphologies with a specialist
    trained_compared: int
    held_out_compared: int
    trained_walking: int      # trained morphologies with grid mean >= WALKS
    trained: int
    held_out_mean: float      # median grid mean over the held-out morphologies (with or without specialists)
    real_steps: float = math.nan     # median over the entry's runs of their own real env steps
    teacher_steps: float = math.nan  # ... and of their teachers' (distillation), NaN where it has none


@dataclass(frozen=True)
class SpecialistScore:
    """One specialist run's final evaluation of its robot."""

    side: str            # the split's side it trained on (robot.morphologies: train or held_out)
    index: int           # its morphology's index on that side (robot.specialist)
    seed: int
    links: int
    mean_displacement: float
    worst_displacement: float
    derivation: str


def specialist_scores(records: Iterable[Record]) -> list[SpecialistScore]:
    """Every specialist run's final evaluation (runs without one yet are left out), by side,
    index and seed: what a study has measured before any universal run has finished."""
    scores = []
    for record in filter(is_specialist, records):
        for score in final_scores(record):
            scores.append(SpecialistScore(record.grammar["side"], int(record.grammar["index"]),
                                          int(record.seed or 0), score.links, score.mean_displacement,
                                          score.worst_displacement, score.derivation))
    return sorted(scores, key=lambda score: (score.side != "train", score.side, score.index, score.seed))


def format_specialists(scores: Sequence[SpecialistScore]) -> str:
    """One line per specialist run, and how many of them walk (grid mean >= ``WALKS`` m)."""
    lines = ["| side | morphology | seed | links | grid mean | worst design | derivation |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {score.side} | {score.index} | {score.seed} | {score.links} | {score.mean_displacement:.2f} m | "
              f"{score.worst_displacement:.2f} m | {score.derivation} |" for score in scores]
    walking = sum(score.mean_displacement >= WALKS for score in scores)
    lines.append(f"\n{walking} of {len(scores)} specialists walk their robot's grid (mean >= {WALKS:g} m)")
    return "\n".join(lines)


def final_scores(record: Record) -> list[MorphologyScore]:
    """The run's final evaluation per morphology; empty when the run has none."""
    return [MorphologyScore(robot.derivation, robot.links, robot.mean_displacement, robot.worst_displacement)
            for robot in record.robots if robot.evaluated]


def is_grammar_run(record: Record) -> bool:
    return record.grammar is not None


def is_specialist(record: Record) -> bool:
    """The reference a morphology is measured against (:func:`study.morphology.grammar_runs.is_specialist`)."""
    return is_grammar_run(record) and bool(record.grammar["specialist"])


def sides(record: Record) -> dict[str, str]:
    """Each robot of the run's record -> trained / held_out / train side, not trained on."""
    return {robot.derivation: robot.side for robot in record.robots}


def compare(records: Iterable[Record]) -> list[Comparison]:
    """Every universal run's final score on every morphology, beside the specialists' median on it."""
    records = [record for record in records if is_grammar_run(record)]
    specialists: dict[str, list[float]] = defaultdict(list)
    for record in filter(is_specialist, records):
        for score in final_scores(record):
            specialists[score.derivation].append(score.mean_displacement)
    comparisons = []
    for record in records:
        if is_specialist(record):
            continue
        side_of = sides(record)
        scores = final_scores(record)
        own = record.real_env_steps if scores else math.nan
        teachers = record.grammar["teacher_steps"] if scores else math.nan
        for score in scores:
            found = specialists.get(score.derivation)
            comparisons.append(Comparison(record.grammar["entry"], score.derivation,
                                          side_of.get(score.derivation, UNTRAINED), score.links,
                                          score.mean_displacement, statistics.median(found) if found else None,
                                          own, teachers, record.name))
    return comparisons


@dataclass(frozen=True)
class MatchedSteps:
    """A universal run and the specialist of one robot it trained on, each at its first periodic
    evaluation once that robot has had ``steps`` real env steps (the universal run's real steps
    over the number of robots it trains on; its robots are drawn evenly on average)."""

    run: str                  # the universal run (its folder under the report's roots)
    derivation: str
    steps: int
    universal: float | None   # grid mean (m); None where the run has not got that far
    specialist: float | None  # the specialists' median grid mean there; None where none got that far


def _first_at(curve: Sequence[tuple[int, float]], steps: float) -> float | None:
    return next((value for at, value in curve if at >= steps), None)


def compare_at_matched_steps(records: Iterable[Record], steps: Sequence[int]) -> list[MatchedSteps]:
    """Every universal run against the specialists on each robot it trained on, at equal real env
    steps *per robot*: the final table compares a universal run with specialists that spent the
    whole budget on one robot each; this says whether sharing one policy slows each robot's
    learning, and from when."""
    if not steps or any(not (isinstance(value, int) and value >= 1) for value in steps):
        raise ValueError(f"steps must be positive integers (real env steps per robot), got {list(steps)!r}")
    records = [record for record in records if is_grammar_run(record)]
    specialists: dict[str, list[list[tuple[int, float]]]] = defaultdict(list)
    for record in filter(is_specialist, records):
        for derivation, curve in record.periodic.items():
            specialists[derivation].append(curve)
    rows = []
    for record in records:
        if is_specialist(record):
            continue
        trained = [derivation for derivation, side in sides(record).items() if side == TRAINED]
        for derivation in trained:
            for per_robot in steps:
                found = [value for curve in specialists.get(derivation, [])
                         if (value := _first_at(curve, per_robot)) is not None]
                rows.append(MatchedSteps(record.name, derivation, per_robot,
                                         _first_at(record.periodic.get(derivation, []), per_robot * len(trained)),
                                         statistics.median(found) if found else None))
    return rows


def format_matched_steps(rows: Sequence[MatchedSteps]) -> str:
    """Per universal run and step count: universal and specialist grid means on each trained
    robot, their means over the robots where both got that far, the median over those robots of
    universal / specialist (robots whose specialist does not move forward left out, as in the
    final table) and on how many of them the universal policy is ahead."""
    lines = ["| universal run | real env steps per robot | universal, per robot (m) | specialist, per robot (m) | "
             "universal mean | specialist mean | universal / specialist (median) | ahead |",
             "|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple[str, int], list[MatchedSteps]] = defaultdict(list)
    for row in rows:
        groups[(row.run, row.steps)].append(row)
    for (run, steps), group in groups.items():
        both = [row for row in group if row.universal is not None and row.specialist is not None]
        if not both:
            continue
        universal = " ".join("-" if row.universal is None else f"{row.universal:.2f}" for row in group)
        specialist = " ".join("-" if row.specialist is None else f"{row.specialist:.2f}" for row in group)
        ratio = _median([row.universal / row.specialist for row in both if row.specialist > 0])
        ahead = sum(row.universal > row.specialist for row in both)
        lines.append(f"| {run} | {steps:,} | {universal} | {specialist} | "
                     f"{statistics.mean(row.universal for row in both):.2f} m | "
                     f"{statistics.mean(row.specialist for row in both):.2f} m ({len(both)} robots) | "
                     f"{_percent(ratio)} | {ahead} of {len(both)} |")
    return "\n".join(lines)


def _median(values: Sequence[float]) -> float:
    values = [value for value in values if not math.isnan(value)]
    return statistics.median(values) if values else math.nan


def summarize(comparisons: Sequence[Comparison]) -> list[EntrySummary]:
    """Per entry (in order of first appearance): the medians and counts of the module docstring.
    An entry with several seeds pools their morphologies."""
    entries: dict[str, list[Comparison]] = defaultdict(list)
    for comparison in comparisons:
        entries[comparison.entry].append(comparison)
    summaries = []
    for entry, rows in entries.items():
        trained = [row for row in rows if row.side == TRAINED]
        held_out = [row for row in rows if row.side == HELD_OUT]
        summaries.append(EntrySummary(
            entry,
            _median([row.ratio for row in trained]), _median([row.ratio for row in held_out]),
            sum(not math.isnan(row.ratio) for row in trained), sum(not math.isnan(row.ratio) for row in held_out),
            sum(row.universal >= WALKS for row in trained), len(trained),
            _median([row.universal for row in held_out]),
            _median(_per_run(rows, "real_steps")), _median(_per_run(rows, "teacher_steps"))))
    return summaries


def _per_run(rows: Sequence[Comparison], field: str) -> list[float]:
    """One value of ``field`` per run of an entry (its rows repeat it once per morphology)."""
    return list({row.run: getattr(row, field) for row in rows}.values())


def format_table(comparisons: Sequence[Comparison], summaries: Sequence[EntrySummary]) -> str:
    """The summary per entry, then one line per entry and morphology."""
    lines = ["| entry | trained: universal / specialist (median) | walks (>= 1 m) | held out, zero-shot: "
             "universal / specialist (median) | held out: grid mean (median) | real env steps |",
             "|---|---|---|---|---|---|"]
    for summary in summaries:
        lines.append(f"| {summary.entry} | {_percent(summary.trained_ratio)} ({summary.trained_compared} compared) | "
                     f"{summary.trained_walking}/{summary.trained} | {_percent(summary.held_out_ratio)} "
                     f"({summary.held_out_compared} compared) | {_metres(summary.held_out_mean)} | "
                     f"{_steps(summary.real_steps, summary.teacher_steps)} |")
    lines += ["", "| entry | side | links | universal grid mean | specialist grid mean | ratio | derivation |",
              "|---|---|---|---|---|---|---|"]
    for row in sorted(comparisons, key=lambda row: (row.entry, row.side, row.links, row.derivation)):
        specialist = "-" if row.specialist is None else f"{row.specialist:.2f} m"
        lines.append(f"| {row.entry} | {row.side} | {row.links} | {row.universal:.2f} m | {specialist} | "
                     f"{_percent(row.ratio)} | {row.derivation} |")
    return "\n".join(lines)


def _percent(value: float) -> str:
    return "-" if math.isnan(value) else f"{100 * value:.0f}%"


def _steps(own: float, teachers: float) -> str:
    """An entry's real env steps: its own, and its teachers' beside them where it was taught."""
    text = "-" if math.isnan(own) else f"{own:,.0f}"
    return text if math.isnan(teachers) else f"{text} + {teachers:,.0f} (teachers)"


def _metres(value: float) -> str:
    """A grid mean, or "-" where there is none (an entry evaluated on no held-out robot)."""
    return "-" if math.isnan(value) else f"{value:.2f} m"
