"""Runs the league's trainings as a background queue: a frozen commit, two runs at a time, resumable.

    git worktree add ../league <commit>          # the code the study measures, frozen
    nohup python study/queue.py --code ../league --runs ../league_runs \\
        --entries se-trpo,se-moe-trpo --seeds 0-4 > ../league_runs/queue.log 2>&1 &
    python study/league/report.py ../league_runs/*  # the table, whenever

Each run is ``<runs>/<entry>/seed<k>``, trained by ``<code>/train.py`` with the entry's overrides
from ``study/league_plan.yaml``, its seed, its budget (``epochs``), ``checkpoint_every=5``
and no progress bar. Runs go seed by seed (every entry's seed 0, then seed 1, ...), so a queue
cut short leaves every entry with the same seeds. A run whose folder holds a checkpoint resumes
from it with the same overrides; one whose checkpoint has reached its budget is skipped once its
final grid evaluation is written (a run stopped during it is resumed, which runs only that). Every
command goes into the run's ``commands.txt`` beside the commit it ran, its output into
``train.log``. Stopping the queue (SIGTERM, Ctrl-C) stops its runs at their epoch's end, each
saving a checkpoint the next queue resumes from.

The runs are niced (``--nice``) so that work in the foreground keeps the cores it asks for.

``--archive DEST`` copies each run's record (config, metrics, commands; its checkpoint only as below) to
``DEST/<entry>/seed<k>`` as it exits and every ``--archive-every`` seconds while it runs
(:func:`~unipolicy_rl.report.runs.archive_run`), so a study cut with its machine keeps what its runs had measured.
``--carry-checkpoints MIB`` also archives each unfinished run's checkpoint where it is at most that many MiB
(an on-policy run's, about 1 MB; not a replay buffer's), and restores a run whose folder has no
checkpoint from the archive's before it starts: a study whose machine is taken back, its run
folders with it, resumes from the committed archive on the next machine. A finished run's
checkpoint leaves the archive and its final policy alone stays, as ``policy.pt`` (what
``algo=distill`` learns from).
``--stop-after MINUTES`` stops the queue that long after it started, as SIGTERM would (runs end at
their epoch's end with a checkpoint, and are archived): on a machine lent for a fixed time, the
records are final before it goes.
``--stop-at-level {a,b,c}`` stops each run once its periodic evaluations have reached that league
level (:data:`study.league.levels.LEVELS`) and ``--stop-from-steps`` real env steps (e.g.
50,000, the first milestone of the league's (d)), and starts no run that already has: a study of
steps to a level spends no core-hours past it, and a wall-time comparison ends where its measure does.
"""

from __future__ import annotations

import argparse
import datetime
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

# Run as a file, the script's folder leads sys.path, where ``queue.py`` would shadow the standard
# library's (which torch imports): the repository root takes its place, before any third-party
# import, and serves ``import study``.
if __package__ in (None, ""):
    sys.path[0] = str(Path(__file__).resolve().parents[1])

import torch  # noqa: E402
import yaml  # noqa: E402

from study.league.levels import LEVELS  # noqa: E402
from study.records import run_evaluations  # noqa: E402
from unipolicy_rl.report.runs import ReportError, archive_run, load_run, restore_run  # noqa: E402
from unipolicy_rl.training.progress import FINAL_EVALUATIONS  # noqa: E402

PLAN = Path(__file__).with_name("league_plan.yaml")
CHECKPOINT = "checkpoint.pt"
FIXED_OVERRIDES = ("checkpoint_every=5", "progress_bar=false")
LEVEL_CHECK_SECONDS = 30.0  # how often a running run's metrics are read for --stop-at-level
LEVELS_BY_NAME = {level.label.strip("()"): level for level in LEVELS}  # "a", "b", "c" -> the league's level


@dataclass(frozen=True)
class Run:
    entry: str
    seed: int
    overrides: tuple[str, ...]
    epochs: int
    folder: Path

    def command(self, python: str) -> list[str]:
        command = [python, "train.py", *self.overrides, f"seed={self.seed}", f"epochs={self.epochs}",
                   *FIXED_OVERRIDES, f"hydra.run.dir={self.folder}"]
        checkpoint = self.folder / CHECKPOINT
        return command + [f"resume={checkpoint}"] if checkpoint.is_file() else command

    def epochs_done(self) -> int:
        checkpoint = self.folder / CHECKPOINT
        if not checkpoint.is_file():
            return 0
        return int(torch.load(checkpoint, map_location="cpu", weights_only=False)["epoch"])

    def reached(self, level: str, from_steps: float = 0.0) -> float | None:
        """The real env steps at which the run first reached league level ``level`` (``a``, ``b``
        or ``c``), once its evaluations have got to ``from_steps`` real steps; None before."""
        if not (self.folder / "metrics.csv").is_file():
            return None
        done = run_evaluations(load_run(self.folder, f"{self.entry}/seed{self.seed}"))
        at = LEVELS_BY_NAME[level].find(done)
        return at.steps if at is not None and done[-1].steps >= from_steps else None


def parse_seeds(text: str) -> list[int]:
    """``0-4`` or ``0,2,5`` (or both: ``0-2,7``)."""
    seeds: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        try:
            seeds.extend(range(int(first), int(last or first) + 1))
        except ValueError:
            raise argparse.ArgumentTypeError(f"--seeds: {part!r} is neither a seed nor a range like 0-4") from None
    return seeds


def frozen_commit(code: Path) -> str:
    """The commit checked out at ``code``; refuses a tree with uncommitted changes (its runs would
    measure code no commit names)."""
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=code,
                            capture_output=True, text=True, check=True).stdout
    if status.strip():
        raise SystemExit(f"error: {code} has uncommitted changes; run the league from a clean worktree of one "
                         f"commit:\n{status}")
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=code, capture_output=True, text=True,
                          check=True).stdout.strip()


def plan_runs(plan: dict, entries: list[str], seeds: list[int], runs: Path) -> list[Run]:
    unknown = [entry for entry in entries if entry not in plan]
    if unknown:
        raise SystemExit(f"error: entries {unknown} are not in the plan; it has {sorted(plan)}")
    return [Run(entry, seed, tuple(plan[entry]["overrides"]), int(plan[entry]["epochs"]),
                runs.resolve() / entry / f"seed{seed}")
            for seed in seeds for entry in entries]


class Queue:
    """At most ``jobs`` runs at once; a stop request is passed on to the running ones."""

    def __init__(self, code: Path, commit: str, jobs: int, nice: int, archive: Path | None = None,
                 archive_every: float = 600.0, stop_after: float | None = None, checkpoint_limit: int = 0,
                 stop_at_level: tuple[str, float] | None = None) -> None:
        self.code, self.commit, self.jobs, self.nice = code, commit, jobs, nice
        self.stop_at_level = stop_at_level  # (level, from real env steps): each run stops once there
        self.level_checked_at = time.monotonic()
        self.checkpoint_limit = checkpoint_limit  # bytes; 0: checkpoints are not archived
        self.stop_at = None if stop_after is None else time.monotonic() + stop_after
        self.archive, self.archive_every, self.archived_at = archive, archive_every, time.monotonic()
        self.running: dict[subprocess.Popen, Run] = {}
        self.stopped_at_level: set[subprocess.Popen] = set()
        self.stopping = False
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._stop)

    def _stop(self, signum, frame) -> None:
        self.stopping = True
        print(f"queue: stopping {len(self.running)} run(s) at their epoch's end", flush=True)
        for process in self.running:
            process.send_signal(signal.SIGTERM)

    def start(self, run: Run) -> None:
        run.folder.mkdir(parents=True, exist_ok=True)
        command = run.command(sys.executable)
        stamp = datetime.datetime.now().isoformat(timespec="seconds")
        with open(run.folder / "commands.txt", "a") as record:
            record.write(f"{stamp} commit {self.commit} (cd {self.code}): {' '.join(command[1:])}\n")
        log = open(run.folder / "train.log", "a")
        environment = {**os.environ, "PYTHONPATH": str(self.code)}
        process = subprocess.Popen(command, cwd=self.code, stdout=log, stderr=subprocess.STDOUT, env=environment,
                                   preexec_fn=lambda: os.nice(self.nice))
        self.running[process] = run
        print(f"{stamp} started {run.entry} seed {run.seed}: {' '.join(command[1:])}", flush=True)

    def wait_for_slot(self) -> None:
        self._reap()  # (also where --stop-after is noticed, before a start)
        while len(self.running) >= self.jobs:
            time.sleep(5)
            self._reap()

    def _reap(self) -> None:
        if self.stop_at is not None and time.monotonic() >= self.stop_at and not self.stopping:
            print("queue: --stop-after reached", flush=True)
            self._stop(signal.SIGTERM, None)
        for process, run in list(self.running.items()):
            code = process.poll()
            if code is not None:
                del self.running[process]
                stamp = datetime.datetime.now().isoformat(timespec="seconds")
                print(f"{stamp} {run.entry} seed {run.seed} exited with {code} (log: {run.folder / 'train.log'})",
                      flush=True)
                self._archive(run)
        if self.stop_at_level and time.monotonic() - self.level_checked_at >= LEVEL_CHECK_SECONDS:
            self.level_checked_at = time.monotonic()
            for process, run in self.running.items():
                steps = None if process in self.stopped_at_level else run.reached(*self.stop_at_level)
                if steps is not None:
                    print(f"{run.entry} seed {run.seed}: level ({self.stop_at_level[0]}) reached at {steps:,.0f} "
                          f"real env steps; stopping it at its epoch's end", flush=True)
                    process.send_signal(signal.SIGTERM)
                    self.stopped_at_level.add(process)
        if self.running and time.monotonic() - self.archived_at >= self.archive_every:
            self.archived_at = time.monotonic()
            for run in self.running.values():
                self._archive(run)

    def _archive(self, run: Run) -> None:
        if self.archive is None:
            return
        try:
            archive_run(run.folder, self.archived(run), self.checkpoint_limit)
        except (ReportError, OSError) as error:  # a run with no epoch yet, a full disk: the queue goes on
            print(f"queue: not archived: {error}", flush=True)

    def archived(self, run: Run) -> Path:
        return self.archive / run.entry / f"seed{run.seed}"

    def restore(self, run: Run) -> None:
        """A run with no checkpoint of its own starts from the archive's, where checkpoints are carried."""
        if not self.checkpoint_limit or (run.folder / CHECKPOINT).is_file():
            return
        if (self.archived(run) / CHECKPOINT).is_file():
            restore_run(self.archived(run), run.folder)
            print(f"{run.entry} seed {run.seed}: restored from {self.archived(run)} at epoch {run.epochs_done()}",
                  flush=True)

    def drain(self) -> None:
        while self.running:
            self._reap()
            time.sleep(5)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", type=Path, required=True, help="a worktree of the frozen commit to run")
    parser.add_argument("--runs", type=Path, required=True, help="where the runs go (<runs>/<entry>/seed<k>)")
    parser.add_argument("--entries", required=True, help="comma-separated entries of the plan")
    parser.add_argument("--seeds", type=parse_seeds, default=parse_seeds("0-4"), help="e.g. 0-4 or 0,3 (0-4)")
    parser.add_argument("--plan", type=Path, default=PLAN, help=f"entries and budgets ({PLAN.name})")
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (2: one per core here)")
    parser.add_argument("--nice", type=int, default=10, help="niceness of the runs (10)")
    parser.add_argument("--archive", type=Path, default=None,
                        help="copy each run's small files here (<archive>/<entry>/seed<k>), e.g. ../league_archive "
                             "(study/records.py then writes their compact records)")
    parser.add_argument("--archive-every", type=float, default=600.0,
                        help="seconds between copies of the running runs' records (600)")
    parser.add_argument("--carry-checkpoints", type=float, default=0.0, metavar="MIB",
                        help="archive checkpoints up to this many MiB too, and restore runs without one from the "
                             "archive (0: off); needs --archive")
    parser.add_argument("--stop-after", type=float, default=None,
                        help="minutes after which the queue stops its runs (at their epoch's end) and starts no more")
    parser.add_argument("--stop-at-level", choices=sorted(LEVELS_BY_NAME), default=None,
                        help="stop each run once it has reached this league level, and start none that has")
    parser.add_argument("--stop-from-steps", type=float, default=0.0,
                        help="with --stop-at-level: not before the run's evaluations reach this many real env "
                             "steps (0)")
    parser.add_argument("--dry-run", action="store_true", help="print what would run, run nothing")
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    if not args.carry_checkpoints >= 0:
        parser.error(f"--carry-checkpoints must be >= 0 MiB, got {args.carry_checkpoints}")
    if args.carry_checkpoints and args.archive is None:
        parser.error("--carry-checkpoints needs --archive (where the checkpoints are carried)")
    if args.stop_after is not None and not args.stop_after >= 0:
        parser.error(f"--stop-after must be >= 0 minutes, got {args.stop_after}")
    if not args.stop_from_steps >= 0:
        parser.error(f"--stop-from-steps must be >= 0 real env steps, got {args.stop_from_steps}")
    if args.stop_from_steps and args.stop_at_level is None:
        parser.error("--stop-from-steps needs --stop-at-level (the level a run stops at)")

    code = args.code.resolve()
    if not (code / "train.py").is_file():
        parser.error(f"--code {code} holds no train.py")
    commit = frozen_commit(code)
    runs = plan_runs(yaml.safe_load(args.plan.read_text()), args.entries.split(","), args.seeds, args.runs)
    archive = args.archive.resolve() if args.archive is not None else None
    queue = Queue(code, commit, args.jobs, args.nice, archive, args.archive_every,
                  None if args.stop_after is None else 60 * args.stop_after, int(args.carry_checkpoints * 2**20),
                  None if args.stop_at_level is None else (args.stop_at_level, args.stop_from_steps))
    print(f"queue: {len(runs)} run(s) of commit {commit} from {code}, {args.jobs} at a time", flush=True)
    for run in runs:
        if queue.stopping:
            break
        if not args.dry_run:
            queue.restore(run)
        done = run.epochs_done()
        steps = None if args.stop_at_level is None else run.reached(args.stop_at_level, args.stop_from_steps)
        if steps is not None:
            print(f"{run.entry} seed {run.seed}: level ({args.stop_at_level}) reached at {steps:,.0f} real env "
                  f"steps ({done} epochs)", flush=True)
            continue
        if done >= run.epochs and any((run.folder / name).is_file() for name in FINAL_EVALUATIONS):
            print(f"{run.entry} seed {run.seed}: done ({done} of {run.epochs} epochs)", flush=True)
            continue
        if done >= run.epochs:  # stopped during its final evaluation: a resume runs only that
            print(f"{run.entry} seed {run.seed}: trained ({done} of {run.epochs} epochs), resumed for its final "
                  f"evaluation", flush=True)
        if args.dry_run:
            print(" ".join(run.command(sys.executable)[1:]))
            continue
        queue.wait_for_slot()
        if not queue.stopping:
            queue.start(run)
    queue.drain()
    return 0


if __name__ == "__main__":
    sys.exit(main())
