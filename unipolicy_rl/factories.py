"""``make_*`` factories that turn the Hydra config into TorchRL parts (TorchRL sota style).

train.py, the checkpoint loader and the evaluation CLI all build their envs and networks
here, so a policy is always rebuilt exactly as it was trained.
"""

from __future__ import annotations

import functools
import signal

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import Compose, EnvBase, RewardSum, TransformedEnv, VecNorm

from unipolicy_rl.envs import BatchedWalkerEnv
from unipolicy_rl.envs.parallel import SleepingParallelEnv
from unipolicy_rl.networks import make_actor, make_critic

NORMALIZED_OBSERVATION = "observation_norm"


def env_kwargs(cfg: DictConfig) -> dict:
    """Keyword arguments of :class:`BatchedWalkerEnv` (all but ``num_robots``) from the config."""
    robot = cfg.robot
    return {
        "design": instantiate(cfg.design),
        "robot": instantiate(robot.settings, _convert_="all"),
        "physics": instantiate(robot.physics),
        "observation": robot.observation,
        "append_design": robot.append_design,
        "reward_weights": instantiate(robot.reward),
        "episode_length": robot.episode_length,
    }


def worker_env(num_robots: int, **kwargs) -> BatchedWalkerEnv:
    """A worker's robots. Ctrl-C (and a scheduler's SIGTERM) reach every process of the job;
    the worker ignores them so that the trainer alone decides when to stop, after the epoch
    in progress. A worker still exits when the trainer goes: its command pipe closes."""
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, signal.SIG_IGN)
    return BatchedWalkerEnv(num_robots, **kwargs)


def make_env(cfg: DictConfig, normalizer: VecNorm | None = None) -> TransformedEnv:
    """``episodes_per_epoch`` robots per step, split over ``workers`` processes, with
    observation normalisation (TorchRL's VecNorm) and episode-reward tracking."""
    episodes, workers = cfg.episodes_per_epoch, cfg.workers
    if workers < 1 or episodes % workers:
        raise ValueError(f"episodes_per_epoch ({episodes}) must be a positive multiple of workers ({workers})")
    kwargs = env_kwargs(cfg)
    if workers == 1:
        base: EnvBase = BatchedWalkerEnv(episodes, **kwargs)
    else:
        base = SleepingParallelEnv(workers, functools.partial(worker_env, episodes // workers, **kwargs))
    # One set of statistics for all robots (reduce_batch_dims), not one per robot.
    normalizer = normalizer or VecNorm(
        in_keys=["observation"], out_keys=[NORMALIZED_OBSERVATION], new_api=True, reduce_batch_dims=True
    )
    return TransformedEnv(base, Compose(normalizer, RewardSum()))


def make_actor_critic(cfg: DictConfig, observation_dim: int, action_dim: int):
    algo = cfg.algo
    actor = make_actor(
        observation_dim,
        action_dim,
        tuple(algo.actor_hidden),
        algo.activation,
        algo.init_log_std,
        observation_key=NORMALIZED_OBSERVATION,
    )
    critic = make_critic(observation_dim, tuple(algo.critic_hidden), algo.activation,
                         observation_key=NORMALIZED_OBSERVATION)
    return actor, critic


def config_from_dict(config: dict) -> DictConfig:
    return OmegaConf.create(config)
