"""The walking robot as an environment on its own: gymnasium's API one robot at a time, TorchRL's
for many robots per step, any design (l, rho) you choose.

    python examples/env_alone.py            # one gymnasium episode, then 32 robots for 100 steps
    python examples/env_alone.py --quick    # 4 robots for 10 steps (seconds)

No policy, no training: random actions, to show the spaces, the info each step reports and the
batch shapes TorchRL sees.
"""

from __future__ import annotations

import argparse

import gymnasium

import unipolicy_rl  # noqa: F401  (registers unipolicy_rl/Walker-v0)
from unipolicy_rl.envs import BatchedWalkerEnv, DesignDistribution


def one_robot(steps: int = 100, seed: int = 0) -> float:
    """A gymnasium episode of one robot at an explicit design; returns its forward displacement (m)."""
    env = gymnasium.make("unipolicy_rl/Walker-v0")  # SE designs by default: a new (l, rho) per reset
    obs, info = env.reset(seed=seed, options={"design": (0.16, 0.55)})  # or fix one: (l in m, rho in kg/m)
    print(f"observation {obs.shape}, action space {env.action_space}")
    env.action_space.seed(seed)
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        if terminated or truncated:
            break
    env.close()
    print(f"forward displacement {info['forward_displacement']:.3f} m, mean speed {info['mean_forward_speed']:.3f} m/s")
    return float(info["forward_displacement"])


def many_robots(robots: int = 32, steps: int = 100) -> tuple[int, ...]:
    """TorchRL's API: many robots stepped together, here all at the DE design."""
    env = BatchedWalkerEnv(num_robots=robots, design=DesignDistribution.fixed(0.175, 0.5), episode_length=steps)
    batch = env.rollout(steps)  # random actions from the action spec
    env.close()
    print(f"batch {tuple(batch.batch_size)}: mean reward {batch['next', 'reward'].mean().item():.4f}")
    return tuple(batch.batch_size)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="4 robots, 10 steps")
    args = parser.parse_args()
    one_robot(steps=10 if args.quick else 100)
    many_robots(robots=4 if args.quick else 32, steps=10 if args.quick else 100)
