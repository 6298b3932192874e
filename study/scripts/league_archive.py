"""Keeps the league's run folders' small files: what the table is computed from outlives the machine.

    python study/scripts/league_archive.py ../league_runs ../league_archive
    python study/records.py ../league_archive study/league/records    # the compact records committed
    python study/league/report.py --out docs/figures/league

A run folder holds a checkpoint and replay buffer of hundreds of MB beside a few small files that
are all the league reads: the composed config (``.hydra/``), ``metrics.csv`` (every epoch's
real env steps, wall time and evaluations), ``commands.txt`` (every command the run was given,
with the commit it ran) and the final evaluation's tables. This copies those small files of every
run under ``RUNS`` to the same relative folder under ``DEST``, replacing an older copy, so a
record can be kept as a study goes on and the table rebuilt from it on any machine; the repository
keeps only its compact form (:mod:`study.records`).
``study/queue.py --archive DEST`` does it as its runs go (every 10 minutes, and when each exits).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from unipolicy_rl.report.runs import ReportError, archive_run, discover


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, help="the league's runs (<runs>/<entry>/seed<k>)")
    parser.add_argument("destination", type=Path, help="where the small files go, e.g. ../league_archive")
    args = parser.parse_args(argv)
    try:
        runs, _ = discover([args.runs], exclude=[args.destination])
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    archived = 0
    for run in runs:
        relative = run.resolve().relative_to(args.runs.resolve())
        try:
            files = archive_run(run, args.destination / relative)
        except ReportError as error:
            print(f"skipped: {error}", file=sys.stderr)
            continue
        archived += 1
        print(f"{relative}: {len(files)} files")
    print(f"archived {archived} of {len(runs)} runs into {args.destination}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
