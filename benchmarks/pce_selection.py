"""Choose a PCE's settings by its forecast error on held-out real branches, not by one-step error.

    python benchmarks/pce_selection.py --episodes 64 --fit-transitions 4800 --test-transitions 1600
        [--candidates pce pce:lags=1 pce_sparse pce_sparse:lags=1 ...] [--horizon 8] [--starts 1000]
    python benchmarks/pce_selection.py <run dir or checkpoint.pt of a model-based run> ...

A one-step error ranks models by how well they predict a step from a real state; training asks
how far a branch of its own length strays when each step starts from the model's own last
prediction (the F-NARX argument, arXiv 2410.07293: choose terms by multi-step forecast error).
This benchmark fits every candidate (``NAME[:key=value,...]``: a world_model yaml and settings of
its model, e.g. ``pce_sparse:order=4,tolerance=0.05,lags=1``) on the same training transitions,
rolls each out open loop with the recorded actions from the same held-out real states
(deterministic: each member's mean, a member drawn per branch as imagination draws it), and
ranks them by the relative error of the branch's displacement at ``--horizon`` steps (default:
the longest branch ``world_model=pce``'s imagination trains on, ``imagination.horizon.end``),
with the one-step figure and the validation error beside it. The machinery (data, memory
columns, split, fit, open-loop measure) is ``branch_accuracy.py``'s; this script only ranks.

The held-out transitions are the data's last ``--test-transitions`` (later episodes than any
fitted on), so the ranking is on states no candidate saw. One thread.
"""

from __future__ import annotations

import argparse
import statistics

import torch
import world_model_setup as setup
from branch_accuracy import add_data_arguments, checked_data, fit_and_measure

DEFAULT_CANDIDATES = ["pce", "pce:lags=1", "pce_sparse", "pce_sparse:lags=1"]


def training_horizon() -> int:
    """The longest branch world_model=pce's imagination trains on (its yaml's ``horizon.end``)."""
    return int(setup.world_model_config("pce").imagination.horizon.end)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_arguments(parser)
    parser.add_argument("--candidates", nargs="+", default=DEFAULT_CANDIDATES, help="NAME[:key=value,...] each")
    parser.add_argument("--horizon", type=int, default=None,
                        help="branch length to rank by (default: world_model=pce's imagination.horizon.end)")
    parser.add_argument("--starts", type=int, default=1000, help="held-out branches per horizon")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    horizon = args.horizon or training_horizon()
    if horizon < 1:
        raise ValueError(f"--horizon must be a positive number of steps, got {horizon}")
    data, fit, test = checked_data(args, args.candidates)
    print(f"{args.run or f'{args.episodes} cached episodes'}: {len(fit)} transitions fit every candidate, "
          f"{len(test)} later ones hold the branches; ranked by the {horizon}-step displacement error")
    horizons = sorted({1, horizon})
    rows = []
    for spec in args.candidates:
        report, measured = fit_and_measure(spec, data, args.fit_transitions, args.test_transitions, horizons,
                                           args.starts, args.seed, sampled=False)
        rows.append((measured[True, horizon]["relative_displacement"], measured[True, 1]["relative_displacement"],
                     statistics.median(report.validation_error.tolist()), report.seconds, spec))
    rows.sort(key=lambda row: (row[0] != row[0], row[0]))  # NaN (every branch faulted) last
    by_one_step = sorted(rows, key=lambda row: row[2])
    print(f"| rank | candidate | rel. err. displacement, {horizon} steps | 1 step | one-step validation error "
          f"(rank) | fit s |")
    print("|---|---|---|---|---|---|")
    for rank, (error, one_step, validation, seconds, spec) in enumerate(rows, 1):
        print(f"| {rank} | {spec} | {error:.3f} | {one_step:.3f} | {validation:.3f} "
              f"({by_one_step.index(rows[rank - 1]) + 1}) | {seconds:.1f} |")
    print(f"winner: {rows[0][4]} ({horizon}-step displacement error {rows[0][0]:.3f}); "
          f"by one-step validation error alone: {by_one_step[0][4]}")


if __name__ == "__main__":
    main()
