"""Report on a sweep (or a run, or a folder of sweeps): figures, a summary table and report.md.

    python -m unipolicy_rl.report multirun/2025-01-01_12-00-00
    python -m unipolicy_rl.report multirun/main multirun/best --out results/   # with reference runs
    python -m unipolicy_rl.report SWEEP --wide-grid 7 --widen 1.0             # a larger wider grid

Bad input (not a sweep, runs of different robots, unreadable files) is one line naming the
path; the exit status is non-zero only when nothing could be reported.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from unipolicy_rl.report.build import DEFAULT_FOLDER, DEFAULT_WIDE_GRID, DEFAULT_WIDEN, build_report
from unipolicy_rl.report.runs import ReportError


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m unipolicy_rl.report", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dirs", type=Path, nargs="+", metavar="DIR",
                        help="sweep folders (multirun/<time>), run folders, or folders holding them")
    parser.add_argument("--out", type=Path, help=f"report folder; default: {DEFAULT_FOLDER}/ in the first DIR")
    parser.add_argument("--wide-grid", type=int, default=DEFAULT_WIDE_GRID, metavar="N",
                        help=f"designs per axis of the generalisation grid (N x N episodes per final policy); "
                             f"0 skips it; default {DEFAULT_WIDE_GRID}")
    parser.add_argument("--widen", type=float, default=DEFAULT_WIDEN, metavar="FRACTION",
                        help=f"how much wider per axis than the evaluation ranges the generalisation grid is; "
                             f"default {DEFAULT_WIDEN} (50%%)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Exit status: 0 when a report was written (whatever it lists as missing), 1 when none could be."""
    args = make_parser().parse_args(argv)
    try:
        report = build_report(args.dirs, args.out, wide_grid=args.wide_grid, widen=args.widen,
                              echo=lambda message: print(message, file=sys.stderr, flush=True))
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"wrote {report.markdown} ({len(report.figures)} figures, {report.summary_csv.name})")
    if report.missing:
        print(f"{len(report.missing)} runs or jobs missing or incomplete: listed at the end of the report")
    return 0


if __name__ == "__main__":
    sys.exit(main())
