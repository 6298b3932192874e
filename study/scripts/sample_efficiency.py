"""Real env steps (and wall time) until the policy walks the design grid: model-based vs model-free.

Reads finished or running training runs (any mix of sweeps and run folders) and, per run, finds
the first periodic real-env grid evaluation that walks the grid (grid mean >= 3 m, every
design >= 1 m; :func:`unipolicy_rl.evaluation.walks_the_grid`). Prints each run, the median
per source, and the ratio of each source's median to the baseline's (SE-TRPO by default),
measured over the same runs. A run that has not walked (yet) counts as taking more steps than any
that did, so a median is only given when at least half the runs of a source walked.

    python train.py -m source=se seed=0,1,2 hydra.sweep.dir=runs/se
    python train.py -m source=moe seed=0,1,2 epochs=30 hydra.sweep.dir=runs/moe
    python study/scripts/sample_efficiency.py runs/se runs/moe

The wall times are those of the runs themselves: compare them only between runs that shared
the machine alike (the raw-physics rate of ``benchmarks/env_throughput.py`` on the same machine
says how fast it was).
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

from unipolicy_rl.report.metrics import first_walking, median_to_walk
from unipolicy_rl.report.runs import load_runs


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("roots", nargs="+", type=Path, help="sweep or run directories")
    parser.add_argument("--baseline", default="se-trpo",
                        help="what the others are compared with: a run name such as se-trpo (the default; runs from "
                             "before runs were named so are grouped by source, e.g. se)")
    args = parser.parse_args(argv)

    reached: dict[str, list[tuple[float, float]]] = defaultdict(list)
    runs_per_source: dict[str, int] = defaultdict(int)
    print(f"{'run':<40} {'source':<12} {'real steps to walk':>18} {'wall s':>8}")
    for run in load_runs(args.roots):
        label = run.source or "?"
        if run.config and run.config.get("world_model") and "moe_thesis" in str(run.overrides) and \
                "run_name" not in run.config:  # (a named run says moe_thesis itself)
            label = f"{label}_thesis"
        runs_per_source[label] += 1
        walked = first_walking(run)
        if walked is None:
            print(f"{run.name:<40} {label:<12} {'not yet':>18} {'-':>8}  (last epoch {run.last_epoch})")
            continue
        reached[label].append(walked)
        print(f"{run.name:<40} {label:<12} {walked[0]:>18,.0f} {walked[1]:>8.0f}")

    print()
    medians = {}
    for label in sorted(runs_per_source):
        values = reached.get(label, [])
        runs = runs_per_source[label]
        steps = median_to_walk([v[0] for v in values], runs)
        seconds = median_to_walk([v[1] for v in values], runs)
        walked = f"{len(values)} of {runs} runs walked"
        if math.isinf(steps):
            print(f"{label}: median not reached ({walked})")
            continue
        medians[label] = (steps, seconds)
        rest = "; the rest count as more than any that walked" if len(values) < runs else ""
        print(f"{label}: median {steps:,.0f} real env steps, {seconds:.0f} s wall ({walked}{rest})")
    baseline = medians.get(args.baseline)
    if baseline:
        for label, (steps, seconds) in medians.items():
            if label != args.baseline:
                print(f"sample_efficiency_ratio {label}/{args.baseline}: {steps / baseline[0]:.3f} real env steps "
                      f"({baseline[0] / steps:.1f}x fewer), {seconds / baseline[1]:.2f} wall time")
    return medians


if __name__ == "__main__":
    main()
