"""Uncertainty quantification of a trained policy over the uncertain design, by polynomial chaos.

    python -m unipolicy_rl.uq runs/se/checkpoint.pt                 # order 4, 6 x 6 nodes, 100 Monte Carlo designs
    python -m unipolicy_rl.uq CKPT --order 3 --nodes 5 --check 200 --out uq/

Runs the policy's deterministic actions in the real env at the Gauss-Legendre nodes of the
design box, fits every observed coordinate at every step as a Legendre PCE in (l, rho)
(:class:`~unipolicy_rl.polynomial_chaos.DesignResponse`), and checks it against Monte Carlo:
episodes at uniformly random designs, compared step by step with the expansion at the same
designs (mean and standard deviation, mean relative error with the thesis' floors, Jensen-
Shannon divergence). Prints the table for the base's forward position and velocity (or any
observation columns, ``--coordinates``), and writes
the mean and 95% band plot (real against expansion) and the expansion's moments of every
coordinate (``design_response.pt``: ``mean`` and ``variance`` ``[steps, features]``, the
coefficients and the basis) into --out (default: a folder "uq" next to the checkpoint).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from unipolicy_rl.command_line import check_checkpoint_arguments, run_checked, run_command_line
from unipolicy_rl.envs import BatchedWalkerEnv
from unipolicy_rl.envs.design import SE_DENSITY_RANGE, SE_LENGTH_RANGE
from unipolicy_rl.envs.reward import BASE_X, BASE_X_DOT
from unipolicy_rl.evaluation import policy_trajectories
from unipolicy_rl.evaluation.accuracy import THESIS_FLOOR, jensen_shannon, plot_bands, relative_error
from unipolicy_rl.polynomial_chaos import DesignResponse, gauss_legendre_designs, total_degree_terms, uniform_designs

# The base leads every observation layout: position xyz, then velocity xyz.
BASE_NAMES = ("base x (m)", "base y (m)", "base z (m)", "base x_dot (m/s)", "base y_dot (m/s)", "base z_dot (m/s)")
DEFAULT_COORDINATES = (BASE_X, BASE_X_DOT)
REPORTED_STEPS = (10, 25, 50, 100)
RATE_SAMPLES = 10_000  # episodes the expansion's speed is timed on


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m unipolicy_rl.uq", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="checkpoint file written by training")
    parser.add_argument("--order", type=int, default=4, help="total degree of the PCE in (l, rho); default 4")
    parser.add_argument("--nodes", type=int,
                        help="Gauss-Legendre nodes per design axis to fit on (nodes^2 episodes); default order + 2")
    parser.add_argument("--check", type=int, default=100,
                        help="Monte Carlo episodes at uniformly random designs to check against; default 100")
    parser.add_argument("--coordinates", type=int, nargs="+", default=list(DEFAULT_COORDINATES), metavar="INDEX",
                        help="observation columns to report and plot; default the base's x and x_dot (0 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the Monte Carlo designs; default 0")
    parser.add_argument("--out", type=Path, help="output folder; default: uq/ next to the checkpoint")
    parser.add_argument("--length-range", type=float, nargs=2, default=SE_LENGTH_RANGE, metavar=("LOW", "HIGH"),
                        help="link length range l (m); default the SE range %(default)s")
    parser.add_argument("--density-range", type=float, nargs=2, default=SE_DENSITY_RANGE, metavar=("LOW", "HIGH"),
                        help="link density range rho (kg/m); default the SE range %(default)s")
    parser.add_argument("--num-robots", type=int, help="robots stepped together; default min(episodes, 32)")
    return parser


def check_arguments(args: argparse.Namespace) -> None:
    """Raises ValueError / FileNotFoundError naming the bad value, before any slow work starts."""
    if args.order < 0:
        raise ValueError(f"--order must be >= 0, got {args.order}")
    if args.nodes is None:
        args.nodes = args.order + 2
    terms = total_degree_terms(2, args.order)
    if args.nodes < 1 or args.nodes**2 < terms:
        raise ValueError(f"--nodes {args.nodes} gives {args.nodes**2} episodes, fewer than the {terms} terms of "
                         f"order {args.order}: use --nodes >= {next(n for n in range(1, 100) if n * n >= terms)}")
    if any(c < 0 for c in args.coordinates):
        raise ValueError(f"--coordinates must be observation column indices >= 0, got {args.coordinates}")
    if args.check < 2:
        raise ValueError(f"--check must be >= 2 (Monte Carlo episodes), got {args.check}")
    check_checkpoint_arguments(args)


def run(args: argparse.Namespace) -> dict:
    """Fits, checks, writes and prints; returns the figures per reported step and the paths written."""
    torch.set_num_threads(1)  # many PyBullet robots, one core: threads only contend
    from unipolicy_rl.checkpoint import load_policy  # imported late: argument errors come first

    loaded = load_policy(args.checkpoint, device="cpu")
    ranges = (tuple(args.length_range), tuple(args.density_range))
    kwargs = dict(loaded.env_kwargs)
    probe = BatchedWalkerEnv(1, **kwargs)
    observation_size = probe.observation_spec["observation"].shape[-1]
    probe.close()
    if max(args.coordinates) >= observation_size:
        raise ValueError(f"--coordinates {args.coordinates}: the policy's observation has {observation_size} columns")
    # ---- the expansion, from episodes at the quadrature nodes
    nodes = gauss_legendre_designs(args.nodes, *ranges)
    started = time.perf_counter()
    fit_episodes, fit_faults, control_period = policy_trajectories(loaded.policy, kwargs, nodes, args.num_robots,
                                                                   progress="nodes")
    physics_seconds = time.perf_counter() - started
    if fit_faults.any():
        print(f"{int(fit_faults.sum())} of {len(nodes)} node episodes had a physics fault and are left out")
    response = DesignResponse.fit(nodes[~fit_faults], fit_episodes[~fit_faults], *ranges, order=args.order)
    # ---- Monte Carlo at random designs, against the expansion at the same designs
    designs = uniform_designs(args.check, *ranges, torch.Generator().manual_seed(args.seed))
    truth, faults, _ = policy_trajectories(loaded.policy, kwargs, designs, args.num_robots, progress="Monte Carlo")
    if faults.any():
        print(f"{int(faults.sum())} of {len(designs)} Monte Carlo episodes had a physics fault and are left out")
    designs, truth = designs[~faults], truth[~faults]
    columns = {c: coordinate_name(c) for c in args.coordinates}
    predicted = response(designs)
    started = time.perf_counter()
    response.sample(RATE_SAMPLES, torch.Generator().manual_seed(args.seed))  # timed on enough designs to measure
    expansion_seconds = time.perf_counter() - started
    figures = compare(response, truth, predicted, columns)
    out_dir = args.out if args.out is not None else args.checkpoint.parent / "uq"
    out_dir.mkdir(parents=True, exist_ok=True)
    plot = plot_bands(truth, {"PCE in (l, rho)": predicted}, columns, out_dir / "uq_bands.png",
                      seconds_per_step=control_period, title=f"real, {len(designs)} random designs, vs PCE")
    moments = out_dir / "design_response.pt"
    torch.save({"mean": response.mean(), "variance": response.variance(),
                "coefficients": response.expansion.coefficients, "basis_indices": response.expansion.basis.indices,
                "length_range": ranges[0], "density_range": ranges[1], "order": args.order}, moments)
    physics_rate = len(nodes) / physics_seconds
    expansion_rate = RATE_SAMPLES / expansion_seconds
    print(f"{args.checkpoint} (epoch {loaded.epoch}): PCE of order {args.order} in (l, rho), "
          f"{response.expansion.basis.terms} terms, fitted on {int((~fit_faults).sum())} episodes at "
          f"{args.nodes} x {args.nodes} Gauss-Legendre nodes; checked on {len(designs)} episodes at random designs")
    print(f"episodes per second: physics {physics_rate:.1f}, expansion {expansion_rate:.0f} "
          f"({expansion_rate / physics_rate:.0f}x)")
    print(format_table(figures))
    print(f"wrote {plot}, {moments}")
    return {"figures": figures, "plot": plot, "moments": moments}


def coordinate_name(column: int) -> str:
    return BASE_NAMES[column] if column < len(BASE_NAMES) else f"observation[{column}]"


def compare(response: DesignResponse, truth: torch.Tensor, predicted: torch.Tensor,
            names: dict[int, str]) -> dict[int, dict[str, dict]]:
    """Per reported step and coordinate: the expansion's mean and standard deviation (from its
    coefficients) against Monte Carlo's, the mean relative error of its episodes (the thesis'
    floors) and the Jensen-Shannon divergence between the two distributions."""
    columns = list(names)
    error = relative_error(truth[..., columns], predicted[..., columns], THESIS_FLOOR)
    divergence = jensen_shannon(truth[..., columns], predicted[..., columns])
    mean, std = response.mean()[:, columns], response.variance()[:, columns].clamp_min(0).sqrt()
    figures = {}
    for step in (s for s in REPORTED_STEPS if s <= truth.shape[1]):
        k = step - 1
        figures[step] = {
            names[c]: {"pce_mean": float(mean[k, i]), "mc_mean": float(truth[:, k, c].mean()),
                         "mc_mean_se": float(truth[:, k, c].std() / len(truth) ** 0.5),
                         "pce_std": float(std[k, i]), "mc_std": float(truth[:, k, c].std()),
                         "relative_error": float(error[k, i]), "jsd_bits": float(divergence[k, i])}
            for i, c in enumerate(columns)
        }
    return figures


def format_table(figures: dict[int, dict[str, dict]]) -> str:
    lines = ["| step | coordinate | mean: PCE | Monte Carlo (+- 2 s.e.) | std: PCE | Monte Carlo | "
             "rel. error | JSD (bits) |", "|---|---|---|---|---|---|---|---|"]
    for step, by_column in figures.items():
        for name, f in by_column.items():
            lines.append(f"| {step} | {name} | {f['pce_mean']:.3f} | {f['mc_mean']:.3f} +- {2 * f['mc_mean_se']:.3f} | "
                         f"{f['pce_std']:.3f} | {f['mc_std']:.3f} | {f['relative_error']:.3f} | "
                         f"{f['jsd_bits']:.3f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict:
    """Programmatic entry: bad arguments raise (ValueError, FileNotFoundError) instead of exiting."""
    return run_checked(make_parser, check_arguments, run, argv)


def cli(argv: Sequence[str] | None = None) -> None:
    """Command-line entry: a bad argument or a missing file is a one-line usage error, not a traceback."""
    run_command_line(make_parser, check_arguments, run, argv)
