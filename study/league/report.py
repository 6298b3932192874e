"""The sample-efficiency league: real env steps (and wall time) to each level, per entry, under one protocol.

    python study/league/report.py                      # the study's records (study/league/records)
    python study/league/report.py RECORDS_OR_RUNS ... [--out outputs/league] [--baseline se-trpo]

Reads run records (:mod:`study.records`) or run folders (read into records on the fly: a study's
runs while they go). Every run evaluates on the same schedule in real env steps
(``evaluation.every_steps``, 2,000 up to ``evaluation.dense_until``, 100,000, then every
``evaluation.then_every_steps``, 10,000): the deterministic policy on the 5 x 5 design grid in
the real env, one episode per design. An entry is a run name (``se-trpo``, ``se-moe-trpo``), its
runs the seeds. Per entry it prints the seeds and, per level (:mod:`study.league.levels`: (a)
first walks the grid, (b) walks and stays walking, (c) SE-TRPO's final level), how many runs
reached it, the median real env steps with a bootstrap 95% interval, the median wall and CPU
time, and how many times fewer real env steps than SE-TRPO and than the best model-free entry; a
run that never reached a level counts as longer than any that did. Then (d): the grid mean and
worst design at 50,000, 100,000 and 300,000 real env steps. Then whether each entry holds what it
reached (:mod:`study.league.holding`): (e) the share of later evaluations at or above each level,
(f) the policy at a fixed budget against SE-TRPO's final median. Writes ``league.png`` (grid mean and
worst design against real env steps, log axis, one band per entry) and ``league.csv`` (the
table's numbers) to ``--out``.

Wall times are the seconds a run spent training (each real epoch's ``time/collect`` and
``time/update``: collecting, fitting, updating), its periodic evaluations and checkpoints left
out: an entry that learns slowly evaluates more often on its way to a level (the schedule is in
real env steps) and is not charged for it. CPU times are the CPU seconds of the same spans
(``time/cpu``: every core, the collector's worker processes counted); runs from before the column
existed have none ("-").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# Run as a file, the script's folder leads sys.path (where ``queue.py`` would shadow the standard
# library's): the repository root takes its place, for ``import study``.
if __package__ in (None, ""):
    sys.path[0] = str(Path(__file__).resolve().parents[2])

from study import records as run_records  # noqa: E402
from study.league.holding import format_holding  # noqa: E402
from study.league.levels import (  # noqa: E402
    BASELINE,
    BOOTSTRAP_SEED,
    RESAMPLES,
    format_league,
    format_runs,
    make_entries,
    plot_league,
    run_result,
    write_csv,
)
from unipolicy_rl.report.runs import ReportError  # noqa: E402

DEFAULT_OUT = Path("outputs") / "league"
RECORDS = Path(__file__).resolve().parent / "records"  # the study's league records


def parse_seeds(text: str) -> list[int]:
    """``0-4,7`` -> [0, 1, 2, 3, 4, 7]."""
    seeds = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        seeds += list(range(int(low), int(high or low) + 1))
    return seeds


def repeated_seeds(records) -> str:
    """The entries' seeds that more than one record holds (two roots with the same runs'
    seeds), named with their records; empty when every entry has each seed once."""
    seen: dict[tuple, list[str]] = {}
    for record in records:
        seen.setdefault((record.entry, record.seed), []).append(record.name)
    return "; ".join(f"{entry} seed {seed} in {', '.join(names)}" for (entry, seed), names in seen.items()
                     if len(names) > 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("roots", nargs="*", type=Path, default=[RECORDS],
                        help="folders of run records or run folders (the study's records)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"where the figure and CSV go ({DEFAULT_OUT})")
    parser.add_argument("--baseline", default=BASELINE, help=f"the entry the others are compared with ({BASELINE})")
    parser.add_argument("--resamples", type=int, default=RESAMPLES, help=f"bootstrap resamples ({RESAMPLES})")
    parser.add_argument("--entries", type=lambda text: text.split(","), default=None, metavar="A,B,...",
                        help="only these entries (run names)")
    parser.add_argument("--seeds", type=parse_seeds, default=None, metavar="N-M,K",
                        help="only these seeds, e.g. 10-15 (seeds no choice was made on)")
    parser.add_argument("--seed", type=int, default=BOOTSTRAP_SEED, help=f"the bootstrap's seed ({BOOTSTRAP_SEED})")
    args = parser.parse_args(argv)

    try:
        records, left_out = run_records.load(args.roots)
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    if args.entries is not None:
        records = [record for record in records if record.entry in args.entries]
    if args.seeds is not None:
        records = [record for record in records if record.seed in args.seeds]
    twice = repeated_seeds(records)
    if twice:
        print(f"error: one set of seeds per entry: {twice}; give the roots of one run per seed", file=sys.stderr)
        return 1
    results = []
    for record in records:
        result = run_result(record)
        if not result.evaluations:
            left_out.append(f"{record.name}: no periodic grid evaluation logged (yet, or evaluation.every_steps=0)")
            continue
        results.append(result)
    for line in left_out:
        print(f"left out {line}", file=sys.stderr)
    if not results:
        print("error: no run with a periodic grid evaluation", file=sys.stderr)
        return 1

    entries = make_entries(results, resamples=args.resamples, seed=args.seed)
    print(format_runs(results))
    print()
    print(format_league(entries, baseline=args.baseline))
    print()
    print(format_holding(entries, baseline=args.baseline))
    figure = plot_league(entries, args.out / "league.png")
    table = write_csv(entries, args.out / "league.csv", baseline=args.baseline)
    print(f"\nwrote {figure} and {table}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
