"""One policy for many robots against a specialist per robot: the table of issue 23, from run folders.

A *specialist* run trains on one morphology of the grammar's split (``robot.specialist``) on
real data; a *universal* run on the first ``robot.training_morphologies`` of its training side
(all of them when unset). A run on a world model's data (``source=moe``) is an entry of its own,
cut to one robot or not, measured against the same specialists (what a world model is worth on
the grammar's robots, beside what it costs in real env steps). Both write their final evaluation per morphology to
``evaluation/morphologies.csv`` (the deterministic policy on the ``evaluation.grid`` design grid,
one row per morphology, its derivation included), which is all this module reads, beside the
run's config. Morphologies are matched by their derivation, so a specialist and a universal
policy are compared on the same robot whatever its index on either side.

Per universal entry (its policy and how many morphologies it trained on) and morphology: the
universal policy's grid mean displacement over the specialist's (the median over specialist
seeds, when there are several). Then per entry: the median of that ratio over the morphologies
it trained on and over the held-out ones (zero-shot), how many of its training
morphologies it walks (grid mean >= ``WALKS`` m), and the real env steps it took: its own, and a
distilled run's teachers' beside them (the issue's budget is the specialists' steps together).
"""

from __future__ import annotations

import csv
import math
import statistics
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from unipolicy_rl.report.metrics import real_env_steps, real_steps_per_epoch
from unipolicy_rl.report.runs import Run

MORPHOLOGIES_CSV = Path("evaluation") / "morphologies.csv"
PERIODIC_CSV = Path("evaluation") / "periodic_morphologies.csv"
WALKS = 1.0  # m of grid mean displacement: a morphology the policy walks
TRAINED, HELD_OUT, UNTRAINED = "trained", "held_out", "train side, not trained on"


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


def specialist_scores(runs: Iterable[Run]) -> list[SpecialistScore]:
    """Every specialist run's final evaluation (runs without one yet are left out), by side,
    index and seed: what a study has measured before any universal run has finished."""
    scores = []
    for run in filter(is_specialist, runs):
        robot = run.config["robot"]
        for score in final_scores(run):
            scores.append(SpecialistScore(str(robot.get("morphologies", "train")), int(robot["specialist"]),
                                          int(run.config.get("seed", 0)), score.links, score.mean_displacement,
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


def final_scores(run: Run) -> list[MorphologyScore]:
    """The run's final evaluation per morphology (the last row of each derivation: an evaluation
    rerun appends); empty when the run has none."""
    path = run.path / MORPHOLOGIES_CSV
    if not path.is_file():
        return []
    with path.open(newline="") as file:
        rows = {row["derivation"]: row for row in csv.DictReader(file)}
    return [MorphologyScore(derivation, int(row["links"]), float(row["mean_forward_displacement"]),
                            float(row["min_forward_displacement"])) for derivation, row in rows.items()]


def is_grammar_run(run: Run) -> bool:
    return bool(run.config) and (run.config.get("robot") or {}).get("kind") == "grammar"


def is_model_based(run: Run) -> bool:
    """Trained on a world model's data (``source.kind: model``)."""
    return (run.config.get("source") or {}).get("kind") == "model"


SPECIALIST_POLICY = "token_mlp"  # issue 23's specialist: an MLP policy on the robot's own observation
SPECIALIST_ALGO = "trpo"  # ... trained by SE-TRPO


def algo_name(run: Run) -> str:
    """The run's learner (``algo.name``; runs from before the setting are TRPO's)."""
    return (run.config.get("algo") or {}).get("name", SPECIALIST_ALGO)


def is_specialist(run: Run) -> bool:
    """The reference a morphology is measured against: SE-TRPO with the padded MLP on that robot
    alone, on real data. (A model-based run, another policy or another learner cut to one robot is
    an entry of its own, measured against it: the universal transformer as one robot's specialist
    says what the architecture costs without the sharing.)"""
    return (is_grammar_run(run) and run.config["robot"].get("specialist") is not None
            and not is_model_based(run) and run.config["policy"]["name"] == SPECIALIST_POLICY
            and algo_name(run) == SPECIALIST_ALGO and not run.config.get("init_policy"))


def entry_name(run: Run) -> str:
    """A run's entry: its policy, the world model it trained on (if any), its learner where it is
    not TRPO, the number of morphologies it trained on (1 for a run cut to one robot), its
    token layout where it is not the default packed one (a padded MLP on another layout is
    another policy), and whether it started from another run's policy (``init_policy``: a
    warm start, measured against the specialists that started from nothing)."""
    robot = run.config["robot"]
    count = 1 if robot.get("specialist") is not None else robot.get("training_morphologies")
    source = f" on {run.config['source']['name']}" if is_model_based(run) else ""
    source += "" if algo_name(run) == SPECIALIST_ALGO else f" with {algo_name(run)}"
    layout = robot.get("token_layout") or "packed"
    layout = "" if layout == "packed" else f", {layout} layout"
    start = ", from another run's policy" if run.config.get("init_policy") else ""
    return f"{run.config['policy']['name']}{source}, {'all' if count is None else count} morphologies{layout}{start}"


def final_real_steps(run: Run) -> float:
    """The run's real env steps at its last logged epoch; NaN where its metrics do not say."""
    try:
        steps = real_env_steps(run)
    except (KeyError, TypeError):  # no real_env_steps column and no epoch size in the config
        return math.nan
    return float(steps[-1]) if len(steps) else math.nan


def teacher_real_steps(run: Run, root: Path = Path(".")) -> float:
    """A distilled run's (``algo=distill``) teachers' real env steps together: what its teaching
    cost before its own steps, which the issue's budget (the specialists' steps together) counts too.
    Read from the teachers' checkpoints (``algo.teachers``, relative to where the run ran: a
    worktree of the repository, whose paths ``root`` stands in for); NaN for another learner or
    where a teacher cannot be read."""
    if algo_name(run) != "distill":
        return math.nan
    # Imported here: reading checkpoints needs torch, which only this question needs.
    from unipolicy_rl.checkpoint import load_checkpoint

    total = 0.0
    for teacher in run.config["algo"].get("teachers") or []:
        path = Path(teacher) if Path(teacher).is_absolute() else root / teacher
        try:
            state = load_checkpoint(path)
            total += state["epoch"] * real_steps_per_epoch(state["config"])
        except (OSError, ValueError, KeyError, RuntimeError):
            return math.nan
    return total


def split_sides(run: Run) -> dict[str, str]:
    """Each derivation of the run's split -> trained / held_out / train side, not trained on."""
    # Imported here: drawing a split builds robots, which only this question needs.
    from unipolicy_rl.envs.config import grammar_morphologies

    robot = run.config["robot"]
    config = OmegaConf.create({**run.config, "robot": {**robot, "specialist": None}})
    split, trained = grammar_morphologies(config, "train")
    if robot.get("specialist") is not None:  # a run cut to one robot trained on that robot only
        side = split.held_out if robot.get("morphologies") == "held_out" else split.train
        trained = [side[int(robot["specialist"])]]
    sides = {" ".join(morphology.derivation()): UNTRAINED for morphology in split.train}
    sides.update({" ".join(morphology.derivation()): HELD_OUT for morphology in split.held_out})
    sides.update({" ".join(morphology.derivation()): TRAINED for morphology in trained})
    return sides


def compare(runs: Iterable[Run], sides_of=split_sides) -> list[Comparison]:
    """Every universal run's final score on every morphology, beside the specialists' median on it."""
    runs = [run for run in runs if is_grammar_run(run)]
    specialists: dict[str, list[float]] = defaultdict(list)
    for run in filter(is_specialist, runs):
        for score in final_scores(run):
            specialists[score.derivation].append(score.mean_displacement)
    comparisons = []
    for run in runs:
        if is_specialist(run):
            continue
        sides = sides_of(run)
        scores = final_scores(run)
        own = final_real_steps(run) if scores else math.nan
        teachers = teacher_real_steps(run) if scores else math.nan
        for score in scores:
            found = specialists.get(score.derivation)
            comparisons.append(Comparison(entry_name(run), score.derivation, sides.get(score.derivation, UNTRAINED),
                                          score.links, score.mean_displacement,
                                          statistics.median(found) if found else None, own, teachers, run.name))
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


def periodic_curves(run: Run) -> dict[str, list[tuple[int, float]]]:
    """The run's periodic evaluations per morphology: derivation -> [(real env steps, grid mean)]
    in order; empty when the run has none."""
    path = run.path / PERIODIC_CSV
    curves: dict[str, list[tuple[int, float]]] = defaultdict(list)
    if path.is_file():
        with path.open(newline="") as file:
            for row in csv.DictReader(file):
                curves[row["derivation"]].append((int(float(row["real_env_steps"])),
                                                  float(row["mean_forward_displacement"])))
    return dict(curves)


def _first_at(curve: Sequence[tuple[int, float]], steps: float) -> float | None:
    return next((value for at, value in curve if at >= steps), None)


def compare_at_matched_steps(runs: Iterable[Run], steps: Sequence[int], sides_of=split_sides) -> list[MatchedSteps]:
    """Every universal run against the specialists on each robot it trained on, at equal real env
    steps *per robot*: the final table compares a universal run with specialists that spent the
    whole budget on one robot each; this says whether sharing one policy slows each robot's
    learning, and from when."""
    if not steps or any(not (isinstance(value, int) and value >= 1) for value in steps):
        raise ValueError(f"steps must be positive integers (real env steps per robot), got {list(steps)!r}")
    runs = [run for run in runs if is_grammar_run(run)]
    specialists: dict[str, list[list[tuple[int, float]]]] = defaultdict(list)
    for run in filter(is_specialist, runs):
        for derivation, curve in periodic_curves(run).items():
            specialists[derivation].append(curve)
    rows = []
    for run in runs:
        if is_specialist(run):
            continue
        trained = [derivation for derivation, side in sides_of(run).items() if side == TRAINED]
        curves = periodic_curves(run)
        for derivation in trained:
            for per_robot in steps:
                found = [value for curve in specialists.get(derivation, [])
                         if (value := _first_at(curve, per_robot)) is not None]
                rows.append(MatchedSteps(run.name, derivation, per_robot,
                                         _first_at(curves.get(derivation, []), per_robot * len(trained)),
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
