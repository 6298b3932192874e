"""The raw rate a benchmark quotes its figures beside: env steps per second of a TorchRL env alone.

Machines differ by 2-3x, so the benchmarks print their absolute figures only beside the rate of
the env itself on the same machine in the same run: random actions, no policy, no learner.
"""

from __future__ import annotations

import time

from torchrl.envs import EnvBase


def random_rollout_rate(env: EnvBase, steps: int, rollouts: int = 1, warmup: int = 5) -> float:
    """Env steps per second (of every env in ``env``'s batch) over ``rollouts`` rollouts of ``steps``
    random actions, after a ``warmup``-step rollout; closes ``env``."""
    env.set_seed(0)
    env.rollout(warmup)
    started = time.perf_counter()
    for _ in range(rollouts):
        env.rollout(steps, break_when_any_done=False)
    seconds = time.perf_counter() - started
    env.close()
    return rollouts * steps * max(env.batch_size.numel(), 1) / seconds
