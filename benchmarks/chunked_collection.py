"""What collecting an epoch in chunks costs (``algo.update_every``), against collecting it whole.

    python benchmarks/chunked_collection.py [--env-id Hopper-v5] [--steps 1000] [--repeats 5]

Each repeat collects one epoch of ``--steps`` real steps of one gymnasium env with SAC's untrained
actor, whole (``algo.update_every=null``) and in chunks of 10 and of 1 step, each chunk handed to
the learner's ``update_chunk`` before the next is collected (the buffer fills; no gradient step is
taken, ``learning_starts`` is out of reach, so only the chunking is timed), the variants in turn
within a repeat. Beside them, in the same run, the raw env: TorchRL's ``GymEnv`` stepping random
actions with no policy. Prints real env steps/s (median of the repeats) and each variant's seconds
per epoch over the whole one's, paired within a repeat. Machines differ by 2-3x: quote the ratios,
beside the raw rate of the same run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from random_rollout import random_rollout_rate
from torchrl.envs import GymEnv

from unipolicy_rl.factories import make_learner, make_real_collector, probe_dimensions

CONF = Path(__file__).resolve().parent.parent / "conf"
VARIANTS = {"whole epoch": None, "chunks of 10": 10, "chunks of 1": 1}


def config(env_id: str, steps: int, update_every: int | None):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=["env=gym", f"env.id={env_id}", "algo=sac", f"env.frames_per_epoch={steps}",
                                            "algo.learning_starts=1000000", "epochs=1",
                                            f"algo.update_every={'null' if update_every is None else update_every}"])


def epoch_seconds(env_id: str, steps: int, update_every: int | None) -> float:
    """Seconds to collect one epoch (the env built and reset before the clock starts)."""
    cfg = config(env_id, steps, update_every)
    torch.manual_seed(0)
    learner = make_learner(cfg, *probe_dimensions(cfg))
    hook = learner.update_chunk if update_every is not None else None
    with make_real_collector(cfg, learner.policy, full_state=False, between_chunks=hook) as collector:
        batches = iter(collector)
        started = time.perf_counter()
        batch = next(batches)
        seconds = time.perf_counter() - started
    assert batch.numel() == steps
    return seconds


def raw_env(env_id: str, steps: int) -> float:
    """Real env steps/s of TorchRL's GymEnv alone: random actions, no policy."""
    return random_rollout_rate(GymEnv(env_id), steps)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="Hopper-v5")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # as train.py
    seconds = {name: [] for name in VARIANTS}
    raw = []
    for _ in range(args.repeats):
        for name, every in VARIANTS.items():
            seconds[name].append(epoch_seconds(args.env_id, args.steps, every))
        raw.append(raw_env(args.env_id, args.steps))
    print(f"{args.env_id}, {args.steps} real steps per epoch, {args.repeats} repeats; raw env "
          f"{statistics.median(raw):,.0f} steps/s")
    result = {"raw_steps_per_second": statistics.median(raw)}
    for name in VARIANTS:
        ratios = [a / b for a, b in zip(seconds[name], seconds["whole epoch"], strict=True)]
        rate = args.steps / statistics.median(seconds[name])
        print(f"  {name:13s} {rate:8,.0f} steps/s   seconds / whole epoch's: {statistics.median(ratios):.2f}")
        result[name] = {"steps_per_second": rate, "ratio": statistics.median(ratios)}
    return result


if __name__ == "__main__":
    main()
