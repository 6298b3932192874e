"""Where a BatchedWalkerEnv N=32 rollout spends its time, by sampling profiler.

    pip install py-spy
    py-spy record -r 500 -f raw -o rollout.txt -- python benchmarks/rollout_profile.py
    python benchmarks/rollout_profile.py --shares rollout.txt

The first call runs the workload (env_throughput's N=32 rollout, 12 times, after the same
warm-up); the second sorts py-spy's samples from the timed rollouts into physics (the
motor command and ``stepSimulation``), state reads, our ``_step``/``_reset``/``_output``, the
replayed policy and TorchRL, and prints each share.
"""

from __future__ import annotations

import argparse
from collections import Counter

import torch
from env_throughput import DE, ReplayedActions

from unipolicy_rl.envs import BatchedWalkerEnv

NUM_ROBOTS, STEPS, ROLLOUTS = 32, 93, 12


def run_workload() -> None:
    torch.set_num_threads(1)
    env = BatchedWalkerEnv(NUM_ROBOTS, DE)
    env.set_seed(0)
    for _ in range(2):  # the warm-up env_throughput does: DE robots are rebuilt, then restored
        env.rollout(2, break_when_any_done=False)
    generator = torch.Generator().manual_seed(0)
    for _ in range(ROLLOUTS):
        actions = torch.rand((STEPS, NUM_ROBOTS, 4), generator=generator) * 2 - 1
        env.rollout(STEPS, ReplayedActions(actions), break_when_any_done=False)
    env.close()


def category(frames: list[str]) -> str:
    leaf = frames[-1]
    if leaf.startswith(("WalkerSimulation.advance ", "WalkerSimulation._drive ")):
        return "physics: motor command and stepSimulation"
    if any(frame.startswith("WalkerSimulation.world_state ") for frame in frames):
        return "state reads"
    if any(frame.startswith("BatchedWalkerEnv._") for frame in frames):
        return "our _step, _reset and _output"
    if any(frame.startswith("ReplayedActions") for frame in frames):
        return "replayed policy"
    return "TorchRL and TensorDict"


def print_shares(path: str) -> None:
    counts, total = Counter(), 0
    with open(path) as samples:
        for line in samples:
            stack, count = line.rsplit(" ", 1)
            frames = stack.split(";")
            # Timed rollouts only: the warm-up's resets rebuild robots, the timed ones restore them.
            if not any(frame.startswith("EnvBase.rollout ") for frame in frames):
                continue
            if any(frame.startswith("WalkerSimulation._build ") for frame in frames):
                continue
            counts[category(frames)] += int(count)
            total += int(count)
    for name, count in counts.most_common():
        print(f"{100 * count / total:6.2f}%  {name}")
    print(f"({total} samples)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shares", metavar="PY_SPY_RAW_FILE", help="summarise a py-spy raw profile of this script")
    args = parser.parse_args()
    if args.shares:
        print_shares(args.shares)
    else:
        run_workload()


if __name__ == "__main__":
    main()
