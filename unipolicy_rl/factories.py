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
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import RewardSum, TransformedEnv
from torchrl.envs.transforms import ObservationNorm

from unipolicy_rl.collectors import (
    ModelBasedCollector,
    RealEpochCollector,
    ShutdownCompleteMultiSyncCollector,
    truncate_last_step,
)
from unipolicy_rl.envs import BatchedWalkerEnv
from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater, TrustRegion
from unipolicy_rl.world_models import DynamicsModel, StateLayout

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


def make_collector(cfg: DictConfig, policy: TensorDictModuleBase, epochs: int,
                   full_state: bool = False) -> Collector | MultiSyncCollector:
    """One epoch (``episodes_per_epoch`` robots x ``episode_length`` steps) per iteration.

    ``workers`` processes each step their share of the robots *and* run the policy on them
    (TorchRL's ``MultiSyncCollector``, weights shared through memory), so the trainer does no
    per-step work; ``workers=1`` collects in this process.

    An epoch is one episode of every robot. The collector's post-processing marks its last
    step truncated and the trainer resets every robot at the start of the next epoch, so
    the envs themselves set no time limit: a limit would make the collector rebuild every
    robot at the end of an epoch only for that reset to rebuild them again. A physics fault
    still ends an episode early, and that robot restarts at once.

    ``full_state`` adds the robots' full state (``state``) to every step, for a world model.
    """
    frames_per_batch = cfg.episodes_per_epoch * cfg.robot.episode_length
    kwargs = {**env_kwargs(cfg), "episode_length": None, "full_state": full_state}
    # The policy needs no env transform (its normaliser is inside it): say so, which also
    # silences TorchRL 0.14's warning that it will add them by itself from 0.15 on.
    common = {"frames_per_batch": frames_per_batch, "total_frames": frames_per_batch * max(epochs, 1),
              "postproc": truncate_last_step, "auto_register_policy_transforms": False}
    if cfg.workers == 1:
        return Collector(functools.partial(training_env, robots_per_worker(cfg), **kwargs), policy, **common)
    make_worker_env = functools.partial(training_env, robots_per_worker(cfg), ignore_signals=True, **kwargs)
    return ShutdownCompleteMultiSyncCollector([make_worker_env] * cfg.workers, policy, cat_results="stack", **common)


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


SOURCE_KINDS = ("real", "model")


def make_training_collector(cfg: DictConfig, policy: TensorDictModuleBase, action_dim: int):
    """The collector ``source.kind`` asks for: real epochs, or real epochs alternating with
    imagined batches from the configured world model (``source.kind: model``)."""
    kind = cfg.source.kind
    if kind not in SOURCE_KINDS:
        raise ValueError(f"source.kind must be one of {SOURCE_KINDS}, got {kind!r}")
    frames_per_batch = cfg.episodes_per_epoch * cfg.robot.episode_length
    model_based = kind == "model"
    real = RealEpochCollector(make_collector(cfg, policy, cfg.epochs, full_state=model_based), cfg.seed, cfg.epochs,
                              frames_per_batch)
    if not model_based:
        return real
    try:
        return _model_based_collector(cfg, real, policy, action_dim)
    except BaseException:
        real.shutdown()  # its worker processes are running already
        raise


def _model_based_collector(cfg: DictConfig, real: RealEpochCollector, policy: TensorDictModuleBase,
                           action_dim: int) -> ModelBasedCollector:
    world_model = cfg.world_model
    reference_env = BatchedWalkerEnv(1, **env_kwargs(cfg), full_state=True)
    reference_env.close()  # only its specs are read
    return ModelBasedCollector(
        real,
        make_dynamics_model(cfg, action_dim),
        instantiate(world_model.trainer),
        policy,
        reference_env,
        instantiate(cfg.robot.reward),
        instantiate(world_model.imagination),
        instantiate(world_model.stopping),
        cfg.seed,
        cfg.robot.episode_length,
    )


def make_dynamics_model(cfg: DictConfig, action_dim: int, device: torch.device | str | None = None) -> DynamicsModel:
    """The world model's dynamics (``world_model.model``), sized for the robot and observation,
    on ``device`` (default: the config's)."""
    if cfg.get("world_model") is None:
        raise ValueError("a model-based source needs a world_model config (e.g. world_model=moe)")
    robot = cfg.robot
    layout = StateLayout.for_env(instantiate(robot.settings, _convert_="all"), robot.observation, robot.append_design,
                                 cfg.world_model.model_state)
    # Partial, then called: Hydra would turn the layout dataclass into a config if passed through it.
    device = resolve_device(cfg.device) if device is None else torch.device(device)
    with torch.device(device):
        return instantiate(cfg.world_model.model, _partial_=True, _convert_="all")(layout=layout, action_dim=action_dim)


def resolve_device(name: str) -> torch.device:
    """``device`` of the config: ``cpu``, ``cuda[:N]``, or ``auto`` (a GPU when there is one).

    It places the world model (its fit and its predictions); the policy, the critic and the
    robots stay on the CPU, where their small networks run fastest next to the physics.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name!r} but torch sees no CUDA GPU here; use device=cpu or device=auto")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}")
    return device


def make_trpo_updater(cfg: DictConfig, actor, critic) -> TRPOUpdater:
    """TRPO loss (GAE) and its update, from ``algo``."""
    algo = cfg.algo
    loss = TRPOLoss(actor, critic, normalize_advantage=algo.normalize_advantage)
    loss.make_value_estimator(gamma=algo.gamma, lmbda=algo.lmbda)
    return TRPOUpdater(
        loss, trust_region=make_trust_region(cfg), critic_lr=algo.critic_lr, critic_epochs=algo.critic_epochs,
        critic_minibatch_size=algo.critic_minibatch_size, generator=torch.Generator().manual_seed(cfg.seed),
    )


def make_trust_region(cfg: DictConfig) -> TrustRegion:
    algo = cfg.algo
    return TrustRegion(max_kl=algo.max_kl, damping=algo.damping, cg_iters=algo.cg_iters,
                       backtrack_factor=algo.backtrack_factor, max_backtracks=algo.max_backtracks)


def probe_dimensions(cfg: DictConfig) -> tuple[int, int]:
    """Observation and action sizes of the configured robot (one robot built and closed)."""
    probe = BatchedWalkerEnv(1, **env_kwargs(cfg))
    dims = probe.observation_spec["observation"].shape[-1], probe.action_spec.shape[-1]
    probe.close()
    return dims
