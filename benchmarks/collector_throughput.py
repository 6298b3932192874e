"""Real-collection throughput of each collector backend, on the work of a training epoch.

    python benchmarks/collector_throughput.py [--robots 20] [--epochs 3] [--repeats 3]

Every variant collects ``--epochs`` epochs of ``--robots`` robots x 100 steps with the default
(untrained) TRPO policy, each epoch reseeded as training reseeds it, after one warm-up epoch
(worker start-up, Ray's cluster start and actor creation are not timed; they are printed apart):

* ``in-process``: TorchRL's ``Collector`` in this process (``workers=1``);
* ``processes x2``: two worker processes (TorchRL's ``MultiSyncCollector``, ``workers=2``);
* ``ray x1`` and ``ray x2``: one and two Ray actors on a local cluster (TorchRL's
  ``RayCollector``, ``collector.backend=ray``).

Beside them, in the same run, the raw batched env: ``BatchedWalkerEnv`` stepping the same robots
with random actions and no policy. Prints real env steps/s (median of the repeats) and each
backend's ratio to the in-process collector, paired within a repeat. Machines differ by 2-3x,
and on a machine with other work the parallel backends cannot use cores it does not have:
quote the ratios, beside the raw rate of the same run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from random_rollout import random_rollout_rate

from unipolicy_rl.collectors import RealEpochCollector
from unipolicy_rl.envs import BatchedWalkerEnv
from unipolicy_rl.factories import make_collector, make_learner, probe_dimensions

CONF = Path(__file__).resolve().parent.parent / "conf"
BACKENDS = {"in-process": ("process", 1), "processes x2": ("process", 2), "ray x1": ("ray", 1),
            "ray x2": ("ray", 2)}


def config(robots: int, backend: str, workers: int):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=[f"episodes_per_epoch={robots}", f"workers={workers}",
                                            f"collector.backend={backend}"])


def collect(robots: int, backend: str, workers: int, epochs: int) -> tuple[float, float]:
    """(real env steps/s over ``epochs`` timed epochs, seconds to start and collect the warm-up epoch)."""
    cfg = config(robots, backend, workers)
    torch.manual_seed(0)
    learner = make_learner(cfg, *probe_dimensions(cfg))
    frames = robots * cfg.robot.episode_length
    started = time.perf_counter()
    collector = RealEpochCollector(make_collector(cfg, learner.policy, epochs + 1), seed=0, epochs=epochs + 1,
                                   frames_per_batch=frames)
    try:
        batches = iter(collector)
        next(batches)
        start_up = time.perf_counter() - started
        started = time.perf_counter()
        for _ in batches:
            collector.update_policy_weights_()  # as training does after every epoch
        return epochs * frames / (time.perf_counter() - started), start_up
    finally:
        collector.shutdown()


def raw_env(robots: int, epochs: int) -> float:
    """Real env steps/s of ``BatchedWalkerEnv`` alone: the same robots, random actions, no policy."""
    return random_rollout_rate(BatchedWalkerEnv(robots, episode_length=None), 100, rollouts=epochs)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=20, help="robots per epoch (a multiple of 2)")
    parser.add_argument("--epochs", type=int, default=3, help="timed epochs per variant and repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=list(BACKENDS))
    args = parser.parse_args(argv)
    if args.robots < 2 or args.robots % 2:
        parser.error(f"--robots must be a positive multiple of 2, got {args.robots}")
    torch.set_num_threads(1)
    rates: dict[str, list[float]] = {name: [] for name in ["raw env", *args.backends]}
    start_up: dict[str, list[float]] = {name: [] for name in args.backends}
    for repeat in range(args.repeats):
        rates["raw env"].append(raw_env(args.robots, args.epochs))
        for name in args.backends:
            rate, seconds = collect(args.robots, *BACKENDS[name], args.epochs)
            rates[name].append(rate)
            start_up[name].append(seconds)
            print(f"repeat {repeat + 1}: {name}: {rate:,.0f} steps/s (start-up and warm-up epoch {seconds:.1f} s)",
                  flush=True)
    base = rates.get("in-process")
    print(f"\n{args.robots} robots x 100 steps per epoch, {args.epochs} timed epochs, median of {args.repeats}")
    print(f"{'variant':14s} {'steps/s':>9s} {'x in-process (paired)':>22s} {'start-up s':>11s}")
    for name, values in rates.items():
        ratio = ("-" if base is None else
                 f"{statistics.median(v / b for v, b in zip(values, base, strict=True)):.2f}")
        started = f"{statistics.median(start_up[name]):.1f}" if name in start_up else "-"
        print(f"{name:14s} {statistics.median(values):9,.0f} {ratio:>22s} {started:>11s}")
    return {name: statistics.median(values) for name, values in rates.items()}


if __name__ == "__main__":
    main()
