"""Throughput of ``MorphologyWalkerEnv`` beside ``BatchedWalkerEnv``, in one process, measured in one run.

    python benchmarks/morphology_env_throughput.py [--robots 16] [--steps 200] [--repeats 3]

Robot-steps per second (median of the repeats; the variants interleaved within each repeat) of:

- ``vertebrate``: ``BatchedWalkerEnv``, the thesis robot, its four hips driven (thesis observation);
- ``tokens, same robot``: ``MorphologyWalkerEnv`` with only the grammar's thesis robot and its hips
  driven, the same physics (tests/test_morphology_env.py), so the difference is reading and
  composing every link's token;
- ``tokens, every hinge``: the thesis robot with all ten hinges driven, as the grammar env drives by default;
- ``tokens, training split``: robots drawn from the default split's 32 training morphologies.

Every variant runs ``--steps`` steps of ``--robots`` robots, random actions drawn before timing,
100-step episodes reset as a collector does (``step_and_maybe_reset``), the reset's rebuilds
included, the design drawn from the SE ranges. The last column is each ratio to ``vertebrate``,
paired within a repeat.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from unipolicy_rl.envs import BatchedWalkerEnv, MorphologyWalkerEnv
from unipolicy_rl.envs.morphology import default_morphologies
from unipolicy_rl.robots.grammar import VERTEBRATE


def robot_steps_per_second(env, steps: int) -> float:
    torch.manual_seed(0)
    actions = env.action_spec.rand((steps,))
    env.set_seed(0)
    td = env.reset()
    start = time.perf_counter()
    for action in actions:
        _, td = env.step_and_maybe_reset(td.set("action", action))
    elapsed = time.perf_counter() - start
    env.close()
    return steps * env.batch_size[0] / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=16)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    split_train = default_morphologies()
    variants = {
        "vertebrate": lambda: BatchedWalkerEnv(args.robots),
        "tokens, same robot": lambda: MorphologyWalkerEnv(args.robots, (VERTEBRATE,), driven_joints=("axial_roll",)),
        "tokens, every hinge": lambda: MorphologyWalkerEnv(args.robots, (VERTEBRATE,)),
        "tokens, training split": lambda: MorphologyWalkerEnv(args.robots, split_train),
    }
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(args.repeats):
        for name, make in variants.items():
            rates[name].append(robot_steps_per_second(make(), args.steps))
    print(f"{args.robots} robots, {args.steps} steps, {args.repeats} repeats; "
          "robot-steps/s (median), ratio to vertebrate")
    for name, values in rates.items():
        ratio = statistics.median(v / base for v, base in zip(values, rates["vertebrate"], strict=True))
        print(f"{name:24s} {statistics.median(values):8.0f} {ratio:6.2f}")


if __name__ == "__main__":
    main()
