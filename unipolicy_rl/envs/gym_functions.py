"""Known rewards and terminations of gymnasium's tasks, as TensorDict modules a world model uses.

A world model that predicts only the next state needs the task's reward and its end from
somewhere: where they are exact functions of ``(observation, action, next observation)``, they
are given (MBPO's and mbrl-lib's ``termination_fns``; mbrl-lib's ``reward_fns``), and the model
learns nothing it could get wrong. Each module reads the real env's keys (``observation``,
``action``, ``("next", "observation")``) and writes ``("next", "reward")`` (float ``[..., 1]``) or
``("next", "terminated")`` (bool ``[..., 1]``), so it checks against the real env's own output
(as the tests do) and plugs into :func:`~unipolicy_rl.world_models.make_world_model`.

The terminations are mbrl-lib's (``mbrl/env/termination_fns.py``), on gymnasium's v5
observations (positions without the root's x):

* Hopper: ends unless every number is finite, ``|obs[1:]| < 100``, the height ``obs[0] > 0.7``
  and the torso's angle ``|obs[1]| < 0.2``;
* Walker2d: ends unless ``0.8 < obs[0] < 2.0`` and ``-1 < obs[1] < 1``;
* InvertedPendulum: ends where the pole's angle ``|obs[1]| > 0.2`` or a number is not finite;
* HalfCheetah (and Pendulum): never.
"""

from __future__ import annotations

import math

import torch
from tensordict.nn import TensorDictModule
from torch import nn

NEXT_OBSERVATION = ("next", "observation")
PENDULUM_MAX_TORQUE = 2.0  # gymnasium's Pendulum-v1 clips its torque to this


class PendulumReward(nn.Module):
    """Pendulum-v1's reward of the step from ``observation`` ``[cos th, sin th, th_dot]`` with
    ``action`` (the torque, clipped as the env clips it): ``-(th^2 + 0.1 th_dot^2 + 0.001 u^2)``,
    ``th`` wrapped to [-pi, pi) (the env charges the state before the step)."""

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        angle = torch.atan2(observation[..., 1], observation[..., 0])
        angle = torch.remainder(angle + math.pi, 2 * math.pi) - math.pi
        torque = action[..., 0].clamp(-PENDULUM_MAX_TORQUE, PENDULUM_MAX_TORQUE)
        cost = angle**2 + 0.1 * observation[..., 2] ** 2 + 0.001 * torque**2
        return (-cost).unsqueeze(-1)


class HopperTermination(nn.Module):
    """Hopper's health check (see the module docstring)."""

    def forward(self, next_observation: torch.Tensor) -> torch.Tensor:
        height, angle = next_observation[..., 0], next_observation[..., 1]
        healthy = (torch.isfinite(next_observation).all(-1) & (next_observation[..., 1:].abs() < 100).all(-1)
                   & (height > 0.7) & (angle.abs() < 0.2))
        return (~healthy).unsqueeze(-1)


class Walker2dTermination(nn.Module):
    """Walker2d's health check (see the module docstring)."""

    def forward(self, next_observation: torch.Tensor) -> torch.Tensor:
        height, angle = next_observation[..., 0], next_observation[..., 1]
        healthy = (height > 0.8) & (height < 2.0) & (angle > -1.0) & (angle < 1.0)
        return (~healthy).unsqueeze(-1)


class InvertedPendulumTermination(nn.Module):
    """InvertedPendulum's end: the pole past 0.2 rad, or a number that is not finite."""

    def forward(self, next_observation: torch.Tensor) -> torch.Tensor:
        upright = torch.isfinite(next_observation).all(-1) & (next_observation[..., 1].abs() <= 0.2)
        return (~upright).unsqueeze(-1)


def pendulum_reward() -> TensorDictModule:
    """Pendulum-v1's reward: ``(observation, action) -> ("next", "reward")``."""
    return TensorDictModule(PendulumReward(), in_keys=["observation", "action"], out_keys=[("next", "reward")])


def termination(module: nn.Module) -> TensorDictModule:
    """A termination check of the next observation as a TensorDict module: ``-> ("next", "terminated")``."""
    return TensorDictModule(module, in_keys=[NEXT_OBSERVATION], out_keys=[("next", "terminated")])


# Each gymnasium id's known termination (by the name before the version), for the envs that have one.
TERMINATIONS = {"Hopper": HopperTermination, "Walker2d": Walker2dTermination,
                "InvertedPendulum": InvertedPendulumTermination}


def known_termination(env_id: str) -> TensorDictModule | None:
    """The known termination of gymnasium's ``env_id`` (``Hopper-v5``), or None for a task that
    never terminates or has none known here."""
    module = TERMINATIONS.get(env_id.split("-")[0])
    return None if module is None else termination(module())


class InvertedPendulumReward(nn.Module):
    """InvertedPendulum-v5's reward: 1 for a step that leaves the pole up, 0 for the one that drops it."""

    def forward(self, next_observation: torch.Tensor) -> torch.Tensor:
        return 1.0 - InvertedPendulumTermination()(next_observation).float()


# Each gymnasium id's exact reward (by the name before the version), in the task's own action units.
REWARDS = {
    "Pendulum": pendulum_reward,
    "InvertedPendulum": lambda: TensorDictModule(InvertedPendulumReward(), in_keys=[NEXT_OBSERVATION],
                                                 out_keys=[("next", "reward")]),
}


def known_reward(env_id: str) -> TensorDictModule | None:
    """The exact reward of gymnasium's ``env_id`` (``Pendulum-v1``), or None where none is known here
    (the MuJoCo locomotion tasks' forward reward is a finite difference of a position the
    observation leaves out: a world model learns it)."""
    make = REWARDS.get(env_id.split("-")[0])
    return None if make is None else make()
