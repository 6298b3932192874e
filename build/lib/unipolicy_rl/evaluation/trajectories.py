"""A policy's real episodes at given designs, as one tensor of observations per design.

The uncertainty quantification of a policy (:mod:`unipolicy_rl.uq`) fits a polynomial chaos
expansion to these episodes and checks it against more of them; rolling the policy in the real
env is evaluation's job, so it lives here, next to the grid evaluation it shares its rollouts with.
"""

from __future__ import annotations

import torch

from unipolicy_rl.envs.design import Design
from unipolicy_rl.evaluation.grid import design_rollouts


def policy_trajectories(policy, env_kwargs: dict, designs: torch.Tensor, num_robots: int | None = None,
                        seed: int = 0, progress: str | None = None) -> tuple[torch.Tensor, torch.Tensor, float]:
    """One real episode of ``policy``'s deterministic actions per design (``designs`` ``[n, 2]``: l, rho).

    Returns the observation after every action, ``[designs, steps, features]``, which
    episodes had a physics fault (``[designs]``; their observations freeze at the fault), and
    the env's control period (s per step)."""
    pairs = [Design(float(length), float(density)) for length, density in designs.tolist()]
    observations, faults, periods = [], [], []
    for batch, rollout, period in design_rollouts(policy, env_kwargs, pairs, num_robots, seed, True, progress):
        observations.append(rollout["next", "observation"][: len(batch)].double())
        faults.append(rollout["next", "physics_fault"][: len(batch)].reshape(len(batch), -1).any(-1))
        periods.append(period)
    return torch.cat(observations), torch.cat(faults), periods[0]
