"""A run's compact record: what the study's reports read of a run folder, in a few small files.

A training run leaves a folder of tens of MB (its metrics, every evaluation, checkpoints); the
league and morphology tables read a few hundred numbers of it. A record keeps those and says what
ran, so the tables rebuild from a clone of a few MB:

- ``record.yaml``: the entry, the seed, what ran (the command-line overrides, the budget in
  epochs, the float precision and threads of the model's fit), whether it trained to its budget,
  its real env steps at the end, the machine label its seconds are comparable under, and for a
  grammar run its entry and specialist in the morphology table;
- ``evaluations.csv``: the periodic grid evaluations (:data:`EVALUATION_COLUMNS`);
- ``commands.txt``: every command the run was given, with the commit it ran (the queue's log);
- grammar runs: ``morphologies.csv`` (the final evaluation per robot and the robot's side of the
  split) and ``periodic_morphologies.csv`` (the periodic evaluations per robot);
- with ``--training-columns``: ``training.csv``, those columns of the run's metrics at the end of
  each epoch, for a diagnosis that reads more than the evaluations (a critic's loss, a temperature);
  a run without some of them (another learner's) keeps those it has, and says which it lacks.

Floats are written as Python writes them (``repr``), so a table read from records is the one read
from the run folders, digit for digit.

    python study/records.py RUNS DEST [--machine LABEL]   # every run under RUNS -> DEST/<its path>
    python study/records.py RUNS DEST --training-columns train/loss_critic,train/alpha
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import yaml

# Run as a file, the script's folder leads sys.path (where ``queue.py`` would shadow the standard
# library's): the repository root takes its place, for ``import study``.
if __package__ in (None, ""):
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from study.morphology import grammar_runs  # noqa: E402
from study.morphology.grammar_runs import RobotScore  # noqa: E402
from unipolicy_rl.report.metrics import column, real_env_steps, training_cpu_seconds, training_seconds  # noqa: E402
from unipolicy_rl.report.runs import COMMANDS, ReportError, Run, load_run  # noqa: E402
from unipolicy_rl.report.runs import discover as discover_runs  # noqa: E402
from unipolicy_rl.training.metrics_file import EVAL_RETURN, GRID_MEAN, GRID_MIN, GRID_WALKING  # noqa: E402

RECORD = "record.yaml"
EVALUATIONS = "evaluations.csv"
MORPHOLOGIES = "morphologies.csv"
PERIODIC = "periodic_morphologies.csv"
TRAINING = "training.csv"
# (mean_return: env=gym runs, whose evaluation is a return; records from before it lack the column)
EVALUATION_COLUMNS = ("real_env_steps", "seconds", "cpu_seconds", "grid_mean", "grid_min", "walking_designs",
                      "mean_return")
MORPHOLOGY_COLUMNS = ("derivation", "side", "links", "mean_displacement", "worst_displacement")
FIT_BFLOAT16 = "model/fit_bfloat16"  # logged by every fit of a run with precision: auto
PERIODIC_COLUMNS = ("real_env_steps", "robot", "mean_displacement")  # robot: its row in morphologies.csv


@dataclass(frozen=True)
class Evaluation:
    """One periodic grid evaluation of a run (the deterministic policy on the design grid)."""

    steps: float  # the run's real env steps when it evaluated
    seconds: float  # wall seconds spent training up to it (evaluations and checkpoints left out)
    grid_mean: float  # m
    grid_min: float  # m, the worst design
    # CPU seconds over the same spans, every core and the worker processes counted: a cost that
    # load on the machine inflates far less than wall time (NaN where the run did not log it)
    cpu_seconds: float = math.nan
    walking_designs: float = math.nan  # designs of the grid that walk (NaN where not logged)
    mean_return: float = math.nan  # env=gym: the deterministic policy's mean return (NaN on the walker)


@dataclass
class Record:
    """What the study's reports read of one run."""

    name: str  # its path under the records' (or runs') root, e.g. se-trpo/seed10
    entry: str  # the run's name (``run_name``: se-moe-trpo)
    seed: int | None
    model_free: bool  # trained on real data only
    step_schedule: bool  # evaluated on the schedule in real env steps (older runs: every N epochs)
    finished: bool  # trained to its budget, its final evaluation written
    budget: int | None  # epochs asked for
    real_env_steps: float  # at its last logged epoch (NaN where its metrics do not say)
    overrides: list[str] = field(default_factory=list)
    precision: str | None = None  # the model fit's float precision (world_model.fit.precision)
    threads: int | None = None  # torch threads of the fit (null: torch's default)
    machine: str | None = None  # runs with the same label ran on one machine at one load: seconds compare
    commands: list[str] = field(default_factory=list)
    evaluations: list[Evaluation] = field(default_factory=list)
    grammar: dict | None = None  # grammar runs: entry, specialist, side, index, teacher_steps
    robots: list[RobotScore] = field(default_factory=list)
    periodic: dict[str, list[tuple[int, float]]] = field(default_factory=dict)  # derivation -> (steps, grid mean)


# -- from a run folder ---------------------------------------------------------------
def run_evaluations(run: Run) -> list[Evaluation]:
    """The run's periodic grid evaluations (rows with a grid mean and worst design), in order; a gym
    task's (rows with a mean return)."""
    if run.rows and EVAL_RETURN in run.columns:
        returns, steps = column(run, EVAL_RETURN), real_env_steps(run)
        seconds, cpu = training_seconds(run), training_cpu_seconds(run)
        return [Evaluation(float(steps[i]), float(seconds[i]), math.nan, math.nan, float(cpu[i]),
                           mean_return=float(returns[i]))
                for i in range(len(run.rows)) if math.isfinite(returns[i])]
    if not run.rows or GRID_MEAN not in run.columns or GRID_MIN not in run.columns:
        return []
    means, mins, walking = column(run, GRID_MEAN), column(run, GRID_MIN), column(run, GRID_WALKING)
    steps, seconds, cpu = real_env_steps(run), training_seconds(run), training_cpu_seconds(run)
    return [Evaluation(float(steps[i]), float(seconds[i]), float(means[i]), float(mins[i]), float(cpu[i]),
                       float(walking[i]))
            for i in range(len(run.rows)) if math.isfinite(means[i]) and math.isfinite(mins[i])]


def is_model_free(run: Run) -> bool:
    """Trained on real data only (``source.kind: real``; a run from before ``source.kind`` existed:
    one without a world model)."""
    source = (run.config or {}).get("source") or {}
    if "kind" in source:
        return source["kind"] == "real"
    return not (run.config or {}).get("world_model")


def on_step_schedule(run: Run) -> bool:
    """Whether the run evaluated on the schedule in real env steps (runs before it evaluated every
    ``evaluation.every`` epochs: its levels are read at that coarser spacing)."""
    return "every_steps" in ((run.config or {}).get("evaluation") or {})


def final_real_steps(run: Run) -> float:
    """The run's real env steps at its last logged epoch; NaN where its metrics do not say."""
    try:
        steps = real_env_steps(run)
    except (KeyError, TypeError):  # no real_env_steps column and no epoch size in the config
        return math.nan
    return float(steps[-1]) if len(steps) else math.nan


def _fit_settings(run: Run) -> tuple[str | None, int | None]:
    """The model fit's precision and threads (``world_model.trainer``), where the run has a world
    model. ``auto`` is named with what the fits ran in (each fit logs ``model/fit_bfloat16``):
    bfloat16 on a CPU with bfloat16 instructions, float32 elsewhere."""
    trainer = (((run.config or {}).get("world_model") or {}).get("trainer")) or {}
    precision = trainer.get("precision")
    if precision == "auto" and FIT_BFLOAT16 in run.columns:
        ran = {value for value in column(run, FIT_BFLOAT16) if math.isfinite(value)}
        precision = f"auto ({'/'.join(sorted('bfloat16' if value else 'float32' for value in ran))})" if ran \
            else precision
    return precision, trainer.get("num_threads")


def from_run(run: Run, machine: str | None = None, teachers_root: Path = Path(".")) -> Record:
    """A run folder's record (read with :func:`~unipolicy_rl.report.runs.load_run`)."""
    precision, threads = _fit_settings(run)
    commands = run.path / COMMANDS
    record = Record(name=run.name, entry=run.source, seed=(run.config or {}).get("seed"),
                    model_free=is_model_free(run), step_schedule=on_step_schedule(run), finished=run.finished,
                    budget=run.epochs, real_env_steps=final_real_steps(run), overrides=list(run.overrides),
                    precision=precision, threads=threads, machine=machine,
                    commands=commands.read_text().splitlines() if commands.is_file() else [],
                    evaluations=run_evaluations(run))
    if grammar_runs.is_grammar_run(run):
        record.grammar, record.robots, record.periodic = grammar_runs.describe(run, teachers_root)
    return record


# -- the files -----------------------------------------------------------------------
def _number(text: str) -> float:
    return math.nan if text == "" else float(text)


def _cell(value: float) -> str | float:
    return "" if isinstance(value, float) and math.isnan(value) else value


def write(record: Record, folder: Path) -> Path:
    """Writes ``record`` into ``folder`` (created); returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    head = {"entry": record.entry, "seed": record.seed, "model_free": record.model_free,
            "step_schedule": record.step_schedule, "finished": record.finished, "budget": record.budget,
            "real_env_steps": None if math.isnan(record.real_env_steps) else record.real_env_steps,
            "overrides": record.overrides, "precision": record.precision, "threads": record.threads,
            "machine": record.machine}
    if record.grammar is not None:
        head["grammar"] = {key: None if isinstance(value, float) and math.isnan(value) else value
                           for key, value in record.grammar.items()}
    (folder / RECORD).write_text(yaml.safe_dump(head, sort_keys=False, width=1000))
    (folder / COMMANDS).write_text("".join(f"{line}\n" for line in record.commands))
    with (folder / EVALUATIONS).open("w", newline="") as file:
        writer = csv.writer(file, lineterminator="\n")
        writer.writerow(EVALUATION_COLUMNS)
        for e in record.evaluations:
            writer.writerow([_cell(value) for value in (e.steps, e.seconds, e.cpu_seconds, e.grid_mean, e.grid_min,
                                                        e.walking_designs, e.mean_return)])
    if record.grammar is not None:
        index = {robot.derivation: i for i, robot in enumerate(record.robots)}
        with (folder / MORPHOLOGIES).open("w", newline="") as file:
            writer = csv.writer(file, lineterminator="\n")
            writer.writerow(MORPHOLOGY_COLUMNS)
            for robot in record.robots:
                writer.writerow([robot.derivation, robot.side, robot.links, _cell(robot.mean_displacement),
                                 _cell(robot.worst_displacement)])
        with (folder / PERIODIC).open("w", newline="") as file:
            writer = csv.writer(file, lineterminator="\n")
            writer.writerow(PERIODIC_COLUMNS)
            for derivation, curve in record.periodic.items():
                writer.writerows([steps, index[derivation], value] for steps, value in curve)
    return folder


def read(folder: Path, name: str) -> Record:
    """The record in ``folder`` (:func:`write`), named ``name``."""
    head = yaml.safe_load((folder / RECORD).read_text())
    with (folder / EVALUATIONS).open(newline="") as file:
        rows = list(csv.DictReader(file))
    evaluations = [Evaluation(_number(row["real_env_steps"]), _number(row["seconds"]), _number(row["grid_mean"]),
                              _number(row["grid_min"]), _number(row["cpu_seconds"]), _number(row["walking_designs"]),
                              _number(row.get("mean_return", "")))
                   for row in rows]
    commands = folder / COMMANDS
    record = Record(name=name, entry=head["entry"], seed=head["seed"], model_free=head["model_free"],
                    step_schedule=head["step_schedule"], finished=head["finished"], budget=head["budget"],
                    real_env_steps=math.nan if head["real_env_steps"] is None else head["real_env_steps"],
                    overrides=head.get("overrides") or [], precision=head.get("precision"),
                    threads=head.get("threads"), machine=head.get("machine"),
                    commands=commands.read_text().splitlines() if commands.is_file() else [],
                    evaluations=evaluations)
    if head.get("grammar") is not None:
        record.grammar = {key: math.nan if value is None and key == "teacher_steps" else value
                          for key, value in head["grammar"].items()}
        with (folder / MORPHOLOGIES).open(newline="") as file:
            record.robots = [RobotScore(row["derivation"], row["side"], int(row["links"]),
                                        _number(row["mean_displacement"]), _number(row["worst_displacement"]))
                             for row in csv.DictReader(file)]
        periodic: dict[str, list[tuple[int, float]]] = {}
        with (folder / PERIODIC).open(newline="") as file:
            for row in csv.DictReader(file):
                derivation = record.robots[int(row["robot"])].derivation
                periodic.setdefault(derivation, []).append((int(row["real_env_steps"]),
                                                            float(row["mean_displacement"])))
        record.periodic = periodic
    return record


# -- many ----------------------------------------------------------------------------
def load(roots: list[Path]) -> tuple[list[Record], list[str]]:
    """Every record under ``roots`` (folders holding a ``record.yaml``), and every run folder there
    read into one on the fly (a study's runs still going); with the reasons runs were left out.
    Each is named by its path under its root, or under the roots' common folder when there are
    several (the root's own name when it is one)."""
    records, left_out = [], []
    for root in roots:
        if not root.is_dir():
            raise ReportError(f"{root}: no such directory")
    base = Path(os.path.commonpath([root.resolve() for root in roots])) if len(roots) > 1 else None
    for root in roots:
        name_root = root if base is None else base
        folders = sorted(path.parent for path in root.rglob(RECORD))
        for folder in folders:
            records.append(read(folder, _name(folder, name_root)))
        if folders:
            continue
        paths, _ = discover_runs([root])
        for path in paths:
            run = load_run(path, _name(path, name_root))
            if run.config is None or run.source is None:
                left_out.append(f"{run.name}: {'; '.join(run.problems) or 'no config'}")
                continue
            if not run.rows and run.problems:  # an unreadable metrics.csv: say why, not "no evaluation yet"
                left_out.append(f"{run.name}: {'; '.join(run.problems)}")
                continue
            records.append(from_run(run))
    return records, left_out


def write_training(run_folder: Path, names: list[str], folder: Path) -> list[str]:
    """``training.csv`` in ``folder``: those of the columns ``names`` that the run's ``metrics.csv``
    has, at the end of each epoch (its real rows; an epoch logged twice, as a resumed run may, by
    its last row). Returns the names it does not have (a SAC run has no TRPO column): no file
    where it has none of them."""
    with (run_folder / "metrics.csv").open(newline="") as file:
        reader = csv.DictReader(file)
        present = [name for name in names if name in (reader.fieldnames or ())]
        rows = [row for row in reader if row.get("imagined") in (None, "", "0.0", "0")]
    missing = [name for name in names if name not in present]
    if not present:
        return missing
    last = {row["epoch"]: row for row in rows}
    with (folder / TRAINING).open("w", newline="") as file:
        writer = csv.writer(file, lineterminator="\n")
        writer.writerow(["epoch", "real_env_steps", *present])
        writer.writerows([row["epoch"], row["real_env_steps"], *(row[name] for name in present)]
                         for row in last.values())
    return missing


def _name(folder: Path, root: Path) -> str:
    folder, root = folder.resolve(), root.resolve()
    return folder.name if folder == root else str(folder.relative_to(root))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, help="a folder of run folders (e.g. <entry>/seed<k>)")
    parser.add_argument("destination", type=Path, help="where the records go, each at its run's path under RUNS")
    parser.add_argument("--machine", default=None,
                        help="a label for runs that ran on one machine at one load (their seconds compare)")
    parser.add_argument("--teachers-root", type=Path, default=Path("."),
                        help="where a distilled run's teachers' paths (algo.teachers) are read from (.)")
    parser.add_argument("--training-columns", default=None,
                        help="comma-separated metrics.csv columns to keep per epoch in training.csv")
    args = parser.parse_args(argv)
    training = [name for name in (args.training_columns or "").split(",") if name]
    try:
        paths, _ = discover_runs([args.runs])
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    written, found = 0, set()
    for path in paths:
        name = _name(path, args.runs)
        run = load_run(path, name)
        if run.config is None or run.source is None:
            print(f"left out {name}: {'; '.join(run.problems) or 'no config'}", file=sys.stderr)
            continue
        folder = write(from_run(run, args.machine, args.teachers_root), args.destination / name)
        if training:
            missing = write_training(path, training, folder)
            found.update(name for name in training if name not in missing)
            if missing:
                print(f"{name}: its metrics.csv has no column {', '.join(missing)} (left out of its training.csv)",
                      file=sys.stderr)
        written += 1
    if training and (nowhere := [name for name in training if name not in found]):
        print(f"error: no run's metrics.csv has the column {', '.join(nowhere)}", file=sys.stderr)
        return 1
    print(f"wrote {written} records under {args.destination}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
