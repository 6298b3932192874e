"""The two entries of a checkpoint command (``python -m unipolicy_rl.evaluate``, ``.uq``).

Each command is a parser, a check of its arguments that raises ValueError / FileNotFoundError
naming the bad value before any slow work, and a ``run``. Called from code the errors are
raised; from the command line they are one-line usage errors, not tracebacks.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Any

from unipolicy_rl.envs import DesignDistribution

Parser = Callable[[], argparse.ArgumentParser]
Check = Callable[[argparse.Namespace], None]
Run = Callable[[argparse.Namespace], Any]


def check_checkpoint_arguments(args: argparse.Namespace) -> None:
    """The arguments every checkpoint command shares: ``--num-robots``, the checkpoint file, and
    the design box (``--length-range``, ``--density-range``)."""
    if args.num_robots is not None and args.num_robots < 1:
        raise ValueError(f"--num-robots must be >= 1, got {args.num_robots}")
    if not args.checkpoint.is_file():
        raise FileNotFoundError(f"checkpoint file not found: {args.checkpoint}")
    # DesignDistribution names an empty or non-positive range.
    DesignDistribution(tuple(args.length_range), tuple(args.density_range))


def run_checked(make_parser: Parser, check_arguments: Check, run: Run, argv: Sequence[str] | None) -> Any:
    """Programmatic entry: bad arguments raise instead of exiting."""
    args = make_parser().parse_args(argv)
    check_arguments(args)
    return run(args)


def run_command_line(make_parser: Parser, check_arguments: Check, run: Run, argv: Sequence[str] | None) -> None:
    """Command-line entry: a bad argument or a missing file exits with the parser's usage error;
    one that only the run finds (a checkpoint that is not ours, an option its policy has no use
    for) with one line naming it, not a traceback."""
    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        check_arguments(args)
    except (ValueError, FileNotFoundError) as error:
        parser.error(str(error))
    try:
        run(args)
    except (ValueError, FileNotFoundError) as error:
        parser.exit(1, f"{parser.prog}: error: {error}\n")
