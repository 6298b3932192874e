"""``make_*`` factories that turn the Hydra config into TorchRL parts (TorchRL sota style).

train.py, the checkpoint loader and the evaluation CLI all build their envs and networks
here, so a policy is always rebuilt exactly as it was trained.
"""

from __future__ import annotations

import functools
import signal

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import RewardSum, TransformedEnv
from torchrl.envs.transforms import ObservationNorm

from unipolicy_rl.envs import BatchedWalkerEnv
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


def training_env(num_robots: int, ignore_signals: bool = False, **kwargs) -> TransformedEnv:
    """One process's robots, with TorchRL's episode-reward tracking.

    In a collector worker (``ignore_signals``) Ctrl-C and a scheduler's SIGTERM, which reach
    every process of the job, are ignored: the trainer alone decides when to stop, after the
    epoch in progress. A worker still exits when the trainer goes (its pipe closes).
    """
    if ignore_signals:
        for number in (signal.SIGINT, signal.SIGTERM):
            signal.signal(number, signal.SIG_IGN)
    return TransformedEnv(BatchedWalkerEnv(num_robots, **kwargs), RewardSum())


def robots_per_worker(cfg: DictConfig) -> int:
    episodes, workers = cfg.episodes_per_epoch, cfg.workers
    if not (isinstance(workers, int) and workers >= 1) or episodes % workers:
        raise ValueError(f"episodes_per_epoch ({episodes}) must be a positive multiple of workers ({workers})")
    return episodes // workers


def make_observation_norm(observation_dim: int, loc: torch.Tensor | None = None,
                          scale: torch.Tensor | None = None) -> ObservationNorm:
    """The policy's input normaliser: ``(observation - loc) / scale``, identity by default."""
    loc = torch.zeros(observation_dim) if loc is None else loc.clone()
    scale = torch.ones(observation_dim) if scale is None else scale.clone()
    return ObservationNorm(loc=loc, scale=scale, standard_normal=True, in_keys=["observation"],
                           out_keys=[NORMALIZED_OBSERVATION])


def make_collector(cfg: DictConfig, policy: TensorDictModuleBase, epochs: int) -> Collector | MultiSyncCollector:
    """One epoch (``episodes_per_epoch`` robots x ``episode_length`` steps) per iteration.

    ``workers`` processes each step their share of the robots *and* run the policy on them
    (TorchRL's ``MultiSyncCollector``, weights shared through memory), so the trainer does no
    per-step work; ``workers=1`` collects in this process.

    An epoch is one episode of every robot. The collector's post-processing marks its last
    step truncated and the trainer resets every robot at the start of the next epoch, so
    the envs themselves set no time limit: a limit would make the collector rebuild every
    robot at the end of an epoch only for that reset to rebuild them again. A physics fault
    still ends an episode early, and that robot restarts at once.
    """
    frames_per_batch = cfg.episodes_per_epoch * cfg.robot.episode_length
    kwargs = {**env_kwargs(cfg), "episode_length": None}
    common = {"frames_per_batch": frames_per_batch, "total_frames": frames_per_batch * max(epochs, 1),
              "postproc": truncate_last_step}
    if cfg.workers == 1:
        return Collector(functools.partial(training_env, robots_per_worker(cfg), **kwargs), policy, **common)
    make_worker_env = functools.partial(training_env, robots_per_worker(cfg), ignore_signals=True, **kwargs)
    return MultiSyncCollector([make_worker_env] * cfg.workers, policy, cat_results="stack", **common)


def truncate_last_step(batch: TensorDictBase) -> TensorDictBase:
    """Ends every episode at the batch's last step (truncated, not terminated), as the time
    limit would. (The collector's own ``set_truncated`` misses reused worker buffers.)"""
    for key in ("truncated", "done"):
        flags = batch.get(("next", key))
        flags[..., -1, :] = True
        batch.set(("next", key), flags)
    return batch


def make_collecting_policy(normalizer: ObservationNorm, actor: TensorDictModuleBase) -> TensorDictSequential:
    """Raw ``observation`` -> normalised -> action: the policy the workers run."""
    return TensorDictSequential(normalizer, actor)


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
