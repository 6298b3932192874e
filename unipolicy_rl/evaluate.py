"""Evaluate a trained policy on a grid of robot designs.

    python -m unipolicy_rl.evaluate runs/se/checkpoint.pt                 # 5 x 5 SE grid, 1 episode each
    python -m unipolicy_rl.evaluate CKPT --grid 7 --stochastic --episodes 4 --out eval/
    python -m unipolicy_rl.evaluate GRAMMAR_CKPT --grid 2 --morphologies held_out   # a robot=grammar policy

Writes designs.csv, heatmap_reward.png and heatmap_displacement.png into --out
(default: a folder "evaluation" next to the checkpoint) and prints a table and a summary.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import torch

from unipolicy_rl.command_line import check_checkpoint_arguments, run_checked, run_command_line
from unipolicy_rl.env_factories import GRAMMAR_SIDES
from unipolicy_rl.envs import DesignDistribution, MorphologyWalkerEnv
from unipolicy_rl.envs.design import SE_DENSITY_RANGE, SE_LENGTH_RANGE
from unipolicy_rl.evaluation import (
    evaluate_on_designs,
    evaluate_on_morphologies,
    format_morphology_summary,
    format_summary,
    format_table,
    plot_heatmaps,
    summarise,
    summarise_morphologies,
    write_csv,
    write_morphology_csvs,
)


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m unipolicy_rl.evaluate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("checkpoint", type=Path, help="checkpoint file written by training")
    parser.add_argument("--grid", type=int, default=5, help="designs per axis (grid x grid designs); default 5")
    parser.add_argument("--episodes", type=int, default=1,
                        help="episodes per design; default 1, since a deterministic policy on one design "
                             "repeats the same episode (use more with --stochastic)")
    parser.add_argument("--out", type=Path, help="output folder; default: evaluation/ next to the checkpoint")
    parser.add_argument("--seed", type=int, default=0, help="seed for the env and for stochastic actions")
    parser.add_argument("--length-range", type=float, nargs=2, default=SE_LENGTH_RANGE, metavar=("LOW", "HIGH"),
                        help="link length range l (m); default the SE range %(default)s")
    parser.add_argument("--density-range", type=float, nargs=2, default=SE_DENSITY_RANGE, metavar=("LOW", "HIGH"),
                        help="link density range rho (kg/m); default the SE range %(default)s")
    parser.add_argument("--num-robots", type=int, help="robots stepped together; default min(episodes in all, 32)")
    parser.add_argument("--morphologies", choices=GRAMMAR_SIDES,
                        help="a robot=grammar policy: the side of its split to evaluate (one deterministic episode "
                             "per morphology and design); default the run's evaluation.morphologies")
    parser.add_argument("--stochastic", action="store_true",
                        help="sample actions instead of taking the policy's deterministic ones")
    return parser


def check_arguments(args: argparse.Namespace) -> None:
    """Raises ValueError / FileNotFoundError naming the bad value, before any slow work starts."""
    if args.grid < 1:
        raise ValueError(f"--grid must be >= 1 (designs per axis), got {args.grid}")
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    check_checkpoint_arguments(args)


def run(args: argparse.Namespace) -> dict:
    """Loads, evaluates, writes the CSV and heatmaps, prints; returns the summary and the paths written."""
    torch.set_num_threads(1)  # many PyBullet robots, one core: threads only contend
    from unipolicy_rl.checkpoint import load_policy  # imported late: argument errors come first

    loaded = load_policy(args.checkpoint, device="cpu")
    designs = DesignDistribution(tuple(args.length_range), tuple(args.density_range)).grid(args.grid)
    out_dir = args.out if args.out is not None else args.checkpoint.parent / "evaluation"
    if loaded.env_class is MorphologyWalkerEnv:
        return _run_morphologies(args, loaded, designs, out_dir)
    if args.morphologies is not None:
        raise ValueError(f"--morphologies {args.morphologies} chooses among a robot=grammar policy's morphologies, and "
                         f"{args.checkpoint} is a policy of the one vertebrate robot: drop --morphologies")
    results = evaluate_on_designs(
        loaded.policy,
        dict(loaded.env_kwargs),
        designs,
        episodes_per_design=args.episodes,
        num_robots=args.num_robots,
        seed=args.seed,
        deterministic=not args.stochastic,
        progress=True,
    )
    csv_path = write_csv(results, out_dir / "designs.csv")
    heatmaps = plot_heatmaps(results, out_dir, title=args.checkpoint.name)
    summary = summarise(results)
    print(format_table(results))
    print(format_summary(summary))
    print(f"wrote {csv_path}, " + ", ".join(str(path) for path in heatmaps))
    return {**summary, "csv": csv_path, "heatmaps": heatmaps}


def _run_morphologies(args: argparse.Namespace, loaded, designs: list, out_dir: Path) -> dict:
    """A ``robot=grammar`` policy on every morphology of one side of its split."""
    from omegaconf import OmegaConf

    from unipolicy_rl.env_factories import morphology_env_kwargs

    cfg = OmegaConf.create(loaded.config)
    side = args.morphologies or OmegaConf.select(cfg, "evaluation.morphologies", default="train")
    results = evaluate_on_morphologies(loaded.policy, morphology_env_kwargs(cfg, side), designs,
                                       num_robots=args.num_robots, seed=args.seed, progress=True)
    summary = summarise_morphologies(results)
    paths = write_morphology_csvs(results, out_dir)
    print(format_summary(summary))
    print(format_morphology_summary(summary))
    print("wrote " + ", ".join(str(path) for path in paths))
    return {**summary, "csv": paths[1], "heatmaps": []}


def main(argv: Sequence[str] | None = None) -> dict:
    """Programmatic entry: bad arguments raise (ValueError, FileNotFoundError) instead of exiting."""
    return run_checked(make_parser, check_arguments, run, argv)


def cli(argv: Sequence[str] | None = None) -> None:
    """Command-line entry: a bad argument or a missing file is a one-line usage error, not a traceback."""
    run_command_line(make_parser, check_arguments, run, argv)


if __name__ == "__main__":
    cli()
