"""How fast each learner learns per second of CPU, beside the physics it learns from.

    python benchmarks/learner_speed.py                     # every learner at its yaml's sizes
    python benchmarks/learner_speed.py --steps 300 --critic-widths 256 1024

For each off-policy learner (``algo=sac|crossq|redq``) and critic width: gradient steps per second
on minibatches drawn from a buffer of real-sized transitions (18 observations, 4 actions), and the
real env steps per second it can keep up with at its yaml's update-to-data ratio (steps/s / UTD).
For TRPO: updates per second on one 1,000-step epoch (GAE, the natural-gradient step, the critic
fit). Beside them, in the same run, the raw physics: real env steps per second of 10 robots
stepped in this process (the collector's work). Quote ratios; absolute figures only beside that
physics rate (machines differ by 2-3x).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from random_rollout import random_rollout_rate
from tensordict import TensorDict

from unipolicy_rl.envs import BatchedWalkerEnv
from unipolicy_rl.factories import make_learner
from unipolicy_rl.policy import NORMALIZED_OBSERVATION

CONF = Path(__file__).resolve().parent.parent / "conf"
OBSERVATIONS, ACTIONS = 18, 4


def config(algo: str, *overrides: str):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=[f"algo={algo}", *overrides])


def transitions(n: int, trpo: bool = False) -> TensorDict:
    """Random transitions shaped as a real epoch's (``[10 robots, n / 10 steps]`` for TRPO)."""
    g = torch.Generator().manual_seed(0)
    flags = torch.zeros(n, 1, dtype=torch.bool)
    data = TensorDict({"observation": torch.randn(n, OBSERVATIONS, generator=g),
                       "action": torch.rand(n, ACTIONS, generator=g) * 2 - 1,
                       "next": {"observation": torch.randn(n, OBSERVATIONS, generator=g),
                                "reward": torch.randn(n, 1, generator=g), "done": flags.clone(),
                                "terminated": flags.clone(), "truncated": flags.clone()}}, batch_size=[n])
    if trpo:  # the behaviour policy's figures TRPO's loss reads, and episode ends
        data["action_log_prob"] = torch.zeros(n)
        data["loc"], data["scale"] = torch.zeros(n, ACTIONS), torch.ones(n, ACTIONS)
        data[NORMALIZED_OBSERVATION] = data["observation"]  # what the collecting policy adds (identity at first)
        data = data.reshape(10, n // 10)
        data["next", "done"][:, -1] = True
        data["next", "truncated"][:, -1] = True
    return data


def gradient_steps_per_second(algo: str, width: int, steps: int) -> tuple[float, float]:
    """(gradient steps/s, the yaml's UTD) of ``algo`` with critics ``width`` wide."""
    torch.manual_seed(0)
    cfg = config(algo, f"algo.critic_hidden=[{width},{width}]", "algo.learning_starts=0",
                 "algo.updates_per_step=1", "algo.buffer_capacity=20000")
    learner = make_learner(cfg, OBSERVATIONS, ACTIONS)
    learner.update(transitions(max(cfg.algo.batch_size, 20)))  # warm-up: fills the buffer, first steps
    data = transitions(steps)
    started = time.perf_counter()
    learner.update(data)  # UTD 1: one gradient step per transition
    seconds = time.perf_counter() - started
    return steps / seconds, float(config(algo).algo.updates_per_step)


def trpo_updates_per_second(updates: int) -> float:
    torch.manual_seed(0)
    learner = make_learner(config("trpo"), OBSERVATIONS, ACTIONS)
    learner.update(transitions(1000, trpo=True))
    started = time.perf_counter()
    for _ in range(updates):
        learner.update(transitions(1000, trpo=True))
    return updates / (time.perf_counter() - started)


def physics_steps_per_second(actions: int = 100) -> float:
    """Real env steps per second of 10 robots, ``actions`` actions each, random actions."""
    return random_rollout_rate(BatchedWalkerEnv(10), actions, warmup=10)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300, help="gradient steps timed per learner and width")
    parser.add_argument("--critic-widths", type=int, nargs="+", default=[256, 1024],
                        help="critic widths to time (hidden units, two layers)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    physics = physics_steps_per_second()
    print(f"raw physics: {physics:,.0f} real env steps/s (10 robots in this process)")
    trpo = trpo_updates_per_second(3)
    print(f"trpo: {trpo:.2f} updates/s on a 1,000-step epoch -> keeps up with {1000 * trpo:,.0f} real steps/s "
          f"({1000 * trpo / physics:.1f}x the physics)")
    results = {"physics": physics, "trpo": trpo}
    for algo in ("sac", "crossq", "redq"):
        for width in args.critic_widths:
            rate, utd = gradient_steps_per_second(algo, width, args.steps)
            results[f"{algo}_{width}"] = rate
            print(f"{algo} critics {width}: {rate:,.0f} gradient steps/s; at UTD {utd:g} it keeps up with "
                  f"{rate / utd:,.1f} real steps/s ({rate / utd / physics:.3f}x the physics)")
    return results


if __name__ == "__main__":
    main()
