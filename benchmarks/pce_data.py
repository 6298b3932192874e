"""Real SE episodes for the PCE benchmarks: random or gait-plus-noise actions, cached in /tmp.

Every robot's design is drawn from the SE ranges at each episode start; actions are uniform
on [-1, 1] (``random``, the thesis' section 6.1.2) or the open-loop gait plus N(0, 0.3^2),
clipped (``gait``: data that walks). Episodes are 100 actions of ``BatchedWalkerEnv(full_state=True)``
robots in this process. Collections are cached under ``/tmp/unipolicy_rl_pce/`` keyed by their
settings; the cache keeps the collection's own rate.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

from unipolicy_rl.envs import BatchedWalkerEnv, PhysicsSettings
from unipolicy_rl.envs.gait import SineGait

CACHE = Path("/tmp/unipolicy_rl_pce")
EPISODE_LENGTH = 100
KEEP = ["state", "action", "design", ("next", "state"), ("next", "physics_fault")]


class Replay:
    def __init__(self, actions: torch.Tensor) -> None:
        self.actions, self.calls = actions, 0

    def __call__(self, tensordict):
        tensordict.set("action", self.actions[self.calls])
        self.calls += 1
        return tensordict


def draw_actions(kind: str, robots: int, generator: torch.Generator) -> torch.Tensor:
    """``[100, robots, 4]`` actions of one round."""
    if kind == "random":
        return torch.rand(EPISODE_LENGTH, robots, 4, generator=generator) * 2 - 1
    period = PhysicsSettings().control_period
    gait = torch.from_numpy(np.stack([SineGait().action(s, period) for s in range(EPISODE_LENGTH)])).float()
    noise = torch.randn(EPISODE_LENGTH, robots, gait.shape[-1], generator=generator) * 0.3
    return (gait.unsqueeze(1) + noise).clamp(-1.0, 1.0)


def collect(episodes: int, kind: str = "random", seed: int = 0, robots: int = 50) -> dict:
    """``{"episodes": TensorDict [E, 100], "seconds", "actions_per_second"}``, from the cache when there."""
    path = CACHE / f"{kind}_e{episodes}_s{seed}_r{robots}.pt"
    if path.exists():
        return torch.load(path, weights_only=False)
    env = BatchedWalkerEnv(robots, full_state=True, episode_length=None)
    env.set_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    chunks = []
    started = time.perf_counter()
    for _ in range(-(-episodes // robots)):
        rollout = env.rollout(EPISODE_LENGTH, Replay(draw_actions(kind, robots, generator)), break_when_any_done=False)
        chunks.append(rollout.select(*KEEP).clone())
    seconds = time.perf_counter() - started
    env.close()
    data = torch.cat(chunks)[:episodes]
    out = {"episodes": data, "seconds": seconds, "actions_per_second": len(chunks) * robots * EPISODE_LENGTH / seconds}
    CACHE.mkdir(parents=True, exist_ok=True)
    torch.save(out, path)
    return out


if __name__ == "__main__":
    torch.set_num_threads(1)
    result = collect(int(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else "random")
    print(result["episodes"].batch_size, f"{result['actions_per_second']:.0f} actions/s")
