"""What the morphology table needs of a grammar run's folder, read once when its record is written.

A *specialist* run trains on one morphology of the grammar's split (``robot.specialist``) on
real data with the padded MLP and TRPO; every other grammar run is an entry measured against the
specialists (:func:`entry_name`). Both write their final evaluation per morphology to
``evaluation/morphologies.csv`` and their periodic ones to ``evaluation/periodic_morphologies.csv``.
Morphologies are matched by their derivation, so a specialist and a universal policy are compared
on the same robot whatever its index on either side. The split's sides are drawn from the run's
config here (it builds robots), so a record carries each robot's side and the table needs no config.
"""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from unipolicy_rl.report.runs import Run

MORPHOLOGIES_CSV = Path("evaluation") / "morphologies.csv"
PERIODIC_CSV = Path("evaluation") / "periodic_morphologies.csv"
TRAINED, HELD_OUT, UNTRAINED = "trained", "held_out", "train side, not trained on"
SPECIALIST_POLICY = "token_mlp"  # issue 23's specialist: an MLP policy on the robot's own observation
SPECIALIST_ALGO = "trpo"  # ... trained by SE-TRPO



@dataclass(frozen=True)
class RobotScore:
    """A grammar run's robot: its side of the split for that run and its final evaluation (NaN
    where the run's final evaluation did not include it)."""

    derivation: str
    side: str
    links: int
    mean_displacement: float = math.nan
    worst_displacement: float = math.nan

    @property
    def evaluated(self) -> bool:
        return not math.isnan(self.mean_displacement)


def is_grammar_run(run: Run) -> bool:
    return bool(run.config) and (run.config.get("robot") or {}).get("kind") == "grammar"


def is_model_based(run: Run) -> bool:
    """Trained on a world model's data (``source.kind: model``)."""
    return (run.config.get("source") or {}).get("kind") == "model"


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
    from unipolicy_rl.report.metrics import real_steps_per_epoch

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
    from unipolicy_rl.env_factories import grammar_morphologies

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


def final_rows(run: Run) -> dict[str, dict]:
    """The run's final evaluation per morphology (the last row of each derivation: an evaluation
    rerun appends); empty when the run has none."""
    path = run.path / MORPHOLOGIES_CSV
    if not path.is_file():
        return {}
    with path.open(newline="") as file:
        return {row["derivation"]: row for row in csv.DictReader(file)}


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


def describe(run: Run, teachers_root: Path = Path(".")):
    """(the record's ``grammar`` block, its robots, its periodic curves) for a grammar run.

    The robots are those of the split it trained on, its final evaluation or its periodic ones
    named, in the split's order (then any other), each with its side of the split for this run
    (:func:`split_sides`; blank for a specialist, the reference, whose split the table never reads)
    and its final evaluation where it has one."""
    # Imported here: the record's types live with the format, which imports this module.

    final, periodic = final_rows(run), periodic_curves(run)
    specialist = is_specialist(run)
    sides = {} if specialist else split_sides(run)
    order = [d for d, side in sides.items() if side == TRAINED or d in final or d in periodic]
    order += [d for d in dict.fromkeys([*final, *periodic]) if d not in sides]
    links = _links(run)
    robots = []
    for derivation in order:
        side = "" if specialist else sides.get(derivation, UNTRAINED)
        if derivation in final:
            row = final[derivation]
            robots.append(RobotScore(derivation, side, int(row["links"]), float(row["mean_forward_displacement"]),
                                     float(row["min_forward_displacement"])))
        else:
            robots.append(RobotScore(derivation, side, links.get(derivation, 0)))
    robot = run.config["robot"]
    index = robot.get("specialist")
    grammar = {"entry": entry_name(run), "specialist": specialist,
               "side": str(robot.get("morphologies", "train")),
               "index": None if index is None else int(index),
               "teacher_steps": teacher_real_steps(run, teachers_root) if final else math.nan}
    return grammar, robots, periodic


def _links(run: Run) -> dict[str, int]:
    """Derivation -> links, from the periodic evaluations (robots the final one left out)."""
    path = run.path / PERIODIC_CSV
    if not path.is_file():
        return {}
    with path.open(newline="") as file:
        return {row["derivation"]: int(row.get("links") or 0) for row in csv.DictReader(file)}
