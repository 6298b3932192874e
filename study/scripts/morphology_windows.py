"""A universal run's periodic evaluations in windows of real env steps per training robot.

    python study/scripts/morphology_windows.py RUN [RUN ...] [--window 30000] [--seed 0]
    python study/scripts/morphology_windows.py RUN [RUN ...] --in-total --window 240000

Each RUN is an entry's run folder (``<runs>/<entry>``, its ``seed<k>`` inside: the run folders, not
their compact records) or a seed's
folder itself. A universal run (``robot=grammar evaluation.morphologies=all``) evaluates every
robot it trained on and every held-out robot on the corner designs every few epochs
(``evaluation/periodic_morphologies.csv``); this groups those evaluations by the real env steps each
training robot had had (the run's steps over its number of training robots, so runs over 8, 16 or 32
robots line up on what each robot got) and prints, per window, the mean over its evaluations of the
training robots' mean forward displacement and of the held-out robots' mean, with the held-out
mean's range over the window. With ``--in-total`` the windows are of the run's real env steps in
all (what the whole run cost: 32 robots at 15,000 steps each have cost what 8 at 60,000 have).
Which robots are which comes from the run's own config, as the run drew them
(``grammar_morphologies``: its training robots first, then the held-out ones).

The figures of docs/grammar.md ("One controller for every joint", "A clock for every joint",
"Many training robots") are this script's output.
"""

from __future__ import annotations

import argparse
import csv
import statistics
from collections import defaultdict
from pathlib import Path

from omegaconf import OmegaConf

from unipolicy_rl.env_factories import grammar_morphologies


def seed_folder(run: Path, seed: int) -> Path:
    folder = run / f"seed{seed}"
    folder = folder if folder.is_dir() else run
    if not (folder / "evaluation" / "periodic_morphologies.csv").is_file():
        raise SystemExit(f"{run}: no evaluation/periodic_morphologies.csv (in {folder}): not a universal run's record")
    return folder


def training_count(folder: Path) -> tuple[int, int]:
    """(training robots, all evaluated robots) of the run's config."""
    cfg = OmegaConf.load(folder / ".hydra" / "config.yaml")
    _, trained = grammar_morphologies(cfg, "train")
    _, evaluated = grammar_morphologies(cfg, cfg.evaluation.morphologies)
    return len(trained), len(evaluated)


# A window: its first step, its evaluations, the training robots' mean, the held-out robots' mean, min, max.
Window = tuple[float, int, float, float, float, float]


def windows(folder: Path, width: float, per_robot: bool = True) -> tuple[int, list[Window]]:
    """(training robots, its windows).

    Windows of real env steps per training robot (``per_robot``), or of the run's real env steps in
    all: per robot, runs over 8, 16 or 32 robots compare on what each robot got; in all, on what
    the whole run cost."""
    trained, evaluated = training_count(folder)
    if evaluated <= trained:
        raise SystemExit(f"{folder}: evaluates no held-out robot (evaluation.morphologies should be all)")
    by_evaluation: dict[float, dict[int, float]] = defaultdict(dict)
    with open(folder / "evaluation" / "periodic_morphologies.csv") as table:
        for row in csv.DictReader(table):
            robots = by_evaluation[float(row["real_env_steps"])]
            robots[int(row["morphology"])] = float(row["mean_forward_displacement"])
    grouped: dict[int, list[dict[int, float]]] = defaultdict(list)
    for steps, robots in sorted(by_evaluation.items()):
        if len(robots) == evaluated:  # (an evaluation a stop cut short is left out)
            grouped[int(steps / (trained if per_robot else 1) // width)].append(robots)
    rows = []
    for index, evaluations in sorted(grouped.items()):
        train = [statistics.mean(robots[i] for i in range(trained)) for robots in evaluations]
        held = [statistics.mean(value for i, value in robots.items() if i >= trained) for robots in evaluations]
        rows.append((index * width, len(evaluations), statistics.mean(train), statistics.mean(held), min(held),
                     max(held)))
    return trained, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--window", type=float, default=30000.0, help="real env steps per training robot (30000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--in-total", action="store_true",
                        help="windows of the run's real env steps in all, not per training robot")
    args = parser.parse_args()
    if not args.window > 0:
        parser.error(f"--window must be positive, got {args.window}")
    steps_column = "steps in all" if args.in_total else "steps/robot"
    print(f"{'run':<36} {'robots':>6} {steps_column:>19} {'evals':>5} {'trained':>8} {'held out (range)':>24}")
    for run in args.runs:
        trained, rows = windows(seed_folder(run, args.seed), args.window, per_robot=not args.in_total)
        for start, count, train, held, low, high in rows:
            span = f"{start:,.0f}-{start + args.window:,.0f}"
            print(f"{run.name:<36} {trained:>6} {span:>19} {count:>5} {train:>8.2f} "
                  f"{f'{held:.2f} ({low:.2f}..{high:.2f})':>24}")


if __name__ == "__main__":
    main()
