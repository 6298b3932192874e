"""Wall time of training against the physics-only lower bound, measured in one run.

    python benchmarks/training_walltime.py                       # 30 epochs of the default (SE) run
    python benchmarks/training_walltime.py --epochs 600          # the full thesis protocol
    python benchmarks/training_walltime.py --epochs 60 source=de workers=1

Runs ``train.py`` (any Hydra overrides after the options) for ``--epochs`` epochs of 10
episodes, and the raw PyBullet loop of ``env_throughput.py`` (one core, same robot and
world) before and after it, so both sides see the same machine. The bound is the time the
raw loop needs for the run's actions; the ratio is the training loop's wall time (collection
plus update, from ``metrics.csv``) over it. The last line is ``training_walltime_ratio: ...``.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from env_throughput import raw_pybullet

from unipolicy_rl.training.metrics_file import COLLECT_TIME, EPOCH_TIMES, FILE_NAME, UPDATE_TIME

ROOT = Path(__file__).resolve().parents[1]


def raw_rates(actions: int, repeats: int) -> list[float]:
    """Raw PyBullet actions/s, ``repeats`` times."""
    return [raw_pybullet(actions)[0] for _ in range(repeats)]


def train(epochs: int, overrides: list[str], run_dir: Path) -> list[dict[str, float]]:
    command = [sys.executable, str(ROOT / "train.py"), f"epochs={epochs}", "evaluation.grid=1", "progress_bar=false",
               f"hydra.run.dir={run_dir}", *overrides]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise RuntimeError(f"train.py failed:\n{result.stderr[-3000:]}")
    with (run_dir / FILE_NAME).open(newline="") as file:
        # Only the timing columns: others are blank on rows that do not log them (eval/ between
        # periodic evaluations), which float() refuses.
        return [{name: float(row[name]) for name in EPOCH_TIMES} for row in csv.DictReader(file)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--raw-actions", type=int, default=3000, help="actions per raw-loop measurement")
    parser.add_argument("--run-dir", type=Path, help="where train.py writes (default: a temporary folder)")
    args, overrides = parser.parse_known_args()
    if args.epochs < 1:
        raise ValueError(f"--epochs must be >= 1, got {args.epochs}")
    if any(override.startswith(("episodes_per_epoch=", "robot.episode_length=")) for override in overrides):
        raise ValueError("this benchmark times the thesis protocol; keep 10 episodes of 100 actions per epoch")

    before = raw_rates(args.raw_actions, 3)
    with tempfile.TemporaryDirectory() as scratch:
        rows = train(args.epochs, overrides, args.run_dir or Path(scratch) / "run")
    after = raw_rates(args.raw_actions, 3)

    raw = statistics.median(before + after)
    actions_per_epoch = 10 * 100  # episodes_per_epoch x episode_length, the thesis protocol
    collect = [row[COLLECT_TIME] for row in rows]
    update = [row[UPDATE_TIME] for row in rows]
    loop = sum(collect) + sum(update)
    bound = len(rows) * actions_per_epoch / raw
    print(f"raw PyBullet (1 core): {raw:.0f} actions/s (before {statistics.median(before):.0f}, "
          f"after {statistics.median(after):.0f})")
    print(f"epochs: {len(rows)}; per epoch median: collect {statistics.median(collect):.3f} s, "
          f"update {statistics.median(update):.3f} s")
    print(f"training loop: {loop:.1f} s; physics-only bound: {bound:.1f} s on one core, {bound / 2:.1f} s on two")
    print(f"600-epoch protocol at this pace: {loop / len(rows) * 600:.0f} s")
    print(f"training_walltime_ratio: {loop / bound:.3f}")


if __name__ == "__main__":
    main()
