"""The policy a run trains and a checkpoint hands over: observation normaliser, then the actor.

Kept apart from the training stack (collectors, world models, learners), so loading a policy to
run or evaluate it imports none of them.
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs.transforms import ObservationNorm

from unipolicy_rl.networks import make_actor, make_critic, make_tanh_actor

NORMALIZED_OBSERVATION = "observation_norm"


def make_observation_norm(observation_dim: int, loc: torch.Tensor | None = None,
                          scale: torch.Tensor | None = None) -> ObservationNorm:
    """The policy's input normaliser: ``(observation - loc) / scale``, identity by default."""
    loc = torch.zeros(observation_dim) if loc is None else loc.clone()
    scale = torch.ones(observation_dim) if scale is None else scale.clone()
    return ObservationNorm(loc=loc, scale=scale, standard_normal=True, in_keys=["observation"],
                           out_keys=[NORMALIZED_OBSERVATION])


def make_collecting_policy(normalizer: ObservationNorm, actor: TensorDictModuleBase) -> TensorDictSequential:
    """Raw ``observation`` -> normalised -> action: the policy the collectors run."""
    return TensorDictSequential(normalizer, actor)


def make_policy_actor(cfg: DictConfig, observation_dim: int, action_dim: int) -> TensorDictModuleBase:
    """The actor ``cfg.algo`` trains, reading the normalised observation: TRPO's Gaussian (its
    std a free parameter), or the off-policy learners' tanh-Gaussian."""
    algo = cfg.algo
    if algo.get("name", "trpo") == "trpo":  # (checkpoints from before algo.name are TRPO's)
        return make_actor(observation_dim, action_dim, tuple(algo.actor_hidden), algo.activation, algo.init_log_std,
                          observation_key=NORMALIZED_OBSERVATION)
    return make_tanh_actor(observation_dim, action_dim, tuple(algo.actor_hidden), algo.activation,
                           observation_key=NORMALIZED_OBSERVATION)


def make_actor_critic(cfg: DictConfig, observation_dim: int, action_dim: int):
    """TRPO's actor and state-value critic from ``cfg.algo``, both reading the normalised observation."""
    algo = cfg.algo
    actor = make_policy_actor(cfg, observation_dim, action_dim)
    critic = make_critic(observation_dim, tuple(algo.critic_hidden), algo.activation,
                         observation_key=NORMALIZED_OBSERVATION)
    return actor, critic
