"""``make_*`` factories that turn the Hydra config into the training run's parts (TorchRL sota style).

train.py builds everything here: the real collector, the learner (``algo``), and for a
model-based source the world model, its trainer, the replay buffer and the imagination. The
policy alone (what a checkpoint hands over) is built in :mod:`unipolicy_rl.policy`, and the env
in :mod:`unipolicy_rl.env_factories`, so loading a policy needs none of this module.
"""

from __future__ import annotations

import functools
import signal
from collections.abc import Callable
from dataclasses import dataclass

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import EnvBase, RewardSum, TransformedEnv

from unipolicy_rl.collectors import (
    Imagination,
    MeanActionRobots,
    RealEpochCollector,
    ShutdownCompleteMultiSyncCollector,
    TransitionBuffer,
    truncate_last_step,
)
from unipolicy_rl.collectors.distributed import make_epoch_ray_collector
from unipolicy_rl.collectors.refits import RefitsWithinEpoch
from unipolicy_rl.env_factories import (
    env_builder,
    env_kind,
    episode_length,
    frames_per_epoch,
    gym_task,
    morphology_env_kwargs,
    steps_per_env_epoch,
)
from unipolicy_rl.envs import BatchedWalkerEnv, MorphologyWalkerEnv
from unipolicy_rl.envs.gym_task import GYM, world_model_reward, world_model_termination
from unipolicy_rl.envs.tokens import TOKEN_MASK, TOKENS
from unipolicy_rl.learners import Learner, OffPolicyLearner, TRPOLearner
from unipolicy_rl.learners.distillation import DistillationLearner, SpecialistTeachers
from unipolicy_rl.learners.off_policy import check_model_based_imagination
from unipolicy_rl.learners.policy_average import AveragedLearner, averaging
from unipolicy_rl.objectives import ClippedStep, TRPOLoss, TRPOUpdater
from unipolicy_rl.observation_statistics import ObservationStatistics
from unipolicy_rl.policy import (
    TOKEN_POLICIES,
    make_actor_critic,
    make_collecting_policy,
    make_observation_norm,
    make_policy_actor,
    make_token_actor,
    make_token_actor_critic,
    make_token_norm,
    policy_architecture,
)
from unipolicy_rl.registry import OFF_POLICY_LEARNERS
from unipolicy_rl.settings import (
    clipped_surrogate,
    distillation_settings,
    make_dynamics_model,
    make_trust_region,
    off_policy_settings,
)
from unipolicy_rl.token_statistics import TokenObservationStatistics
from unipolicy_rl.validation import check_settings
from unipolicy_rl.world_models import Dynamics, check_background_fit
from unipolicy_rl.world_models.trainer import Trainer


def training_env(num_robots: int, ignore_signals: bool = False, env_class: type[EnvBase] = BatchedWalkerEnv,
                 **kwargs) -> TransformedEnv:
    """One process's robots (``env_class(num_robots, **kwargs)``), with TorchRL's episode-reward tracking.

    In a collector worker (``ignore_signals``) Ctrl-C and a scheduler's SIGTERM, which reach
    every process of the job, are ignored: the trainer alone decides when to stop, after the
    epoch in progress. A worker still exits when the trainer goes (its pipe closes).
    """
    if ignore_signals:
        for number in (signal.SIGINT, signal.SIGTERM):
            signal.signal(number, signal.SIG_IGN)
    env = env_class(num_robots, **kwargs)
    if isinstance(env, TransformedEnv):  # a gym task's env, already transformed: one more transform
        env.append_transform(RewardSum())
        return env
    return TransformedEnv(env, RewardSum())


def one_env_epoch(batch: TensorDictBase) -> TensorDictBase:
    """A gym task's epoch, ``[steps]``, as ``[1, steps]`` with its last step truncated."""
    return truncate_last_step(batch.unsqueeze(0))


def robots_per_worker(cfg: DictConfig) -> int:
    # validation's rules for the two keys (a direct caller may not have run validate_config).
    check_settings(cfg, "episodes_per_epoch", "workers")
    return cfg.episodes_per_epoch // cfg.workers


def make_collector(cfg: DictConfig, policy: TensorDictModuleBase, epochs: int,
                   full_state: bool = False, chunks_per_epoch: int | None = None) -> Collector | MultiSyncCollector:
    """One epoch (``episodes_per_epoch`` robots x ``episode_length`` steps) per iteration.

    ``workers`` processes each step their share of the robots *and* run the policy on them
    (TorchRL's ``MultiSyncCollector``, weights shared through memory), so the trainer does no
    per-step work; ``workers=1`` collects in this process. With ``collector.backend=ray`` the
    workers are Ray actors instead (TorchRL's ``RayCollector``), on a local cluster or on the one
    at ``collector.ray_address``.

    An epoch is one episode of every robot. The collector's post-processing marks its last
    step truncated and the trainer resets every robot at the start of the next epoch, so
    the envs themselves set no time limit: a limit would make the collector rebuild every
    robot at the end of an epoch only for that reset to rebuild them again. A physics fault
    still ends an episode early, and that robot restarts at once.

    ``full_state`` adds the robots' full state (``state``) to every step, for a world model.
    The env is the config's robot's (:func:`~unipolicy_rl.env_factories.env_builder`): the
    vertebrate's ``BatchedWalkerEnv``, or for ``robot=grammar`` a ``MorphologyWalkerEnv``, whose
    link tokens already hold every link's state (a world model reads them; ``full_state`` adds
    nothing there).

    For ``env=gym`` the epoch is ``env.frames_per_epoch`` steps of one gymnasium env, in this
    process, its episodes ending at the task's own time limit or termination; the batch is
    ``[1, steps]``, shaped as a walker's ``[robots, steps]``.

    ``chunks_per_epoch`` (``algo.update_every``) makes each batch one of that many chunks of the
    epoch's steps of every env, without the epoch's post-processing (:func:`epoch_postproc`), which
    :class:`RealEpochCollector` applies to the chunks joined; None: each batch is the epoch.
    """
    frames_per_batch = frames_per_epoch(cfg)
    env_class, kwargs = env_builder(cfg)
    postproc = epoch_postproc(cfg)
    if chunks_per_epoch is not None:
        if not (isinstance(chunks_per_epoch, int) and chunks_per_epoch >= 1
                and frames_per_batch % chunks_per_epoch == 0):
            raise ValueError(f"{frames_per_batch} real env steps per epoch do not split into {chunks_per_epoch!r} "
                             f"chunks")
        frames_per_batch, postproc = frames_per_batch // chunks_per_epoch, None
    total_frames = frames_per_batch * (chunks_per_epoch or 1) * max(epochs, 1)
    if env_kind(cfg) == GYM:
        return Collector(functools.partial(training_env, 1, env_class=env_class, **kwargs), policy,
                         frames_per_batch=frames_per_batch, total_frames=total_frames,
                         postproc=postproc, auto_register_policy_transforms=False)
    kwargs = {**kwargs, "episode_length": None}
    if env_class is BatchedWalkerEnv:
        kwargs["full_state"] = full_state
    else:
        kwargs["env_class"] = env_class
    # The policy needs no env transform (its normaliser is inside it): say so, which also
    # silences TorchRL 0.14's warning that it will add them by itself from 0.15 on.
    common = {"frames_per_batch": frames_per_batch, "total_frames": total_frames,
              "postproc": postproc, "auto_register_policy_transforms": False}
    if cfg.collector.backend == "ray":  # one Collector per Ray actor (TorchRL's RayCollector)
        make_worker_env = functools.partial(training_env, robots_per_worker(cfg), ignore_signals=True, **kwargs)
        return make_epoch_ray_collector([make_worker_env] * cfg.workers, policy, frames_per_batch=frames_per_batch,
                                        total_frames=total_frames, postproc=postproc,
                                        address=cfg.collector.ray_address)
    if cfg.workers == 1:
        return Collector(functools.partial(training_env, robots_per_worker(cfg), **kwargs), policy, **common)
    make_worker_env = functools.partial(training_env, robots_per_worker(cfg), ignore_signals=True, **kwargs)
    return ShutdownCompleteMultiSyncCollector([make_worker_env] * cfg.workers, policy, cat_results="stack", **common)


def make_real_collector(cfg: DictConfig, policy: TensorDictModuleBase, full_state: bool,
                        between_chunks: Callable[[TensorDictBase], object] | None = None) -> RealEpochCollector:
    """Real epochs of whole episodes, reseeded per epoch; ``full_state`` adds the robots' full
    state to every step (what a world model fits on). ``collector.mean_action_robots`` of each
    epoch's robots act with the policy's mean action (:class:`MeanActionRobots`). With
    ``algo.update_every`` the epoch comes in chunks of that many steps of every env, each handed to
    ``between_chunks`` (an off-policy learner's ``update_chunk``) before the next is collected."""
    frames_per_batch = frames_per_epoch(cfg)
    if robots := OmegaConf.select(cfg, "collector.mean_action_robots", default=0):
        policy = MeanActionRobots(policy, robots)
    check_settings(cfg, "algo", "env", "robot", "workers", "collector")  # validation's rule for update_every
    chunks = chunks_per_epoch(cfg)
    if chunks is not None and between_chunks is None:
        raise ValueError(f"algo.update_every={cfg.algo.update_every} collects the epoch in chunks for a learner to "
                         f"step between them: pass its update_chunk as between_chunks")
    collector = make_collector(cfg, policy, cfg.epochs, full_state=full_state, chunks_per_epoch=chunks)
    return RealEpochCollector(collector, cfg.seed, cfg.epochs, frames_per_batch, chunks_per_epoch=chunks,
                              between_chunks=between_chunks if chunks is not None else None,
                              postproc=epoch_postproc(cfg) if chunks is not None else None)


def chunks_per_epoch(cfg: DictConfig) -> int | None:
    """The chunks ``algo.update_every`` (an off-policy learner's env steps between its rounds of
    gradient steps) splits each env's epoch into (1 where it is the whole epoch); None without it."""
    every = OmegaConf.select(cfg, "algo.update_every", default=None)
    return None if every is None else steps_per_env_epoch(cfg) // every


def epoch_postproc(cfg: DictConfig) -> Callable[[TensorDictBase], TensorDictBase]:
    """What ends an epoch's batch: its last step truncated (a gym task's one env also gains the
    robots' dimension)."""
    return one_env_epoch if env_kind(cfg) == GYM else truncate_last_step


def chunk_as_env_batch(cfg: DictConfig) -> Callable[[TensorDictBase], TensorDictBase]:
    """A chunk of the epoch as ``[envs, steps]`` (a gym task's one env's chunk is ``[steps]``),
    its last step left as it is: the episode goes on in the next chunk."""
    return add_env_dimension if env_kind(cfg) == GYM else as_it_is


def add_env_dimension(batch: TensorDictBase) -> TensorDictBase:
    return batch.unsqueeze(0)


def as_it_is(batch: TensorDictBase) -> TensorDictBase:
    return batch


def make_refits_within_epoch(cfg: DictConfig, learner: OffPolicyLearner, world: WorldModelParts,
                             policy: TensorDictModuleBase, epoch: int) -> RefitsWithinEpoch | None:
    """MBPO's refits while the epoch is collected (``imagination.refit_every``), the real
    collector's ``between_chunks`` from ``epoch`` on (counted from 1); None without the setting."""
    every = OmegaConf.select(cfg, "imagination.refit_every", default=None)
    if every is None:
        return None
    check_settings(cfg, "imagination", "algo", "env", "robot", "source")  # validation's rule for refit_every
    return RefitsWithinEpoch(learner, world, policy, cfg.seed, every, steps_per_env_epoch(cfg),
                             chunk_as_env_batch(cfg), epoch)


@dataclass
class WorldModelParts:
    """What a model-based run adds to a real one: the dynamics, the trainer that fits them, the
    replay buffer of real transitions they fit on, and the imagination that rolls the policy
    through them."""

    model: Dynamics
    trainer: Trainer
    buffer: TransitionBuffer
    imagination: Imagination


def make_world_model_parts(cfg: DictConfig, action_dim: int) -> WorldModelParts:
    """``world_model`` (model and trainer) and ``imagination`` (settings and stopping rule) of a model source."""
    model = make_dynamics_model(cfg, action_dim)
    settings = instantiate(cfg.imagination)
    env_class, kwargs = env_builder(cfg)
    if env_class is BatchedWalkerEnv:
        kwargs["full_state"] = True
    reference_env = env_class(1, **kwargs)
    reference_env.close()  # only its specs are read
    if env_kind(cfg) == GYM:  # the task's known reward and termination, or the model's learned heads
        task = gym_task(cfg)
        reward, termination = world_model_reward(task), world_model_termination(task)
    else:
        reward, termination = instantiate(cfg.robot.reward), None
    imagination = Imagination(model, reference_env, reward, settings, cfg.seed, episode_length(cfg),
                              termination=termination)
    buffer = TransitionBuffer.for_model(settings.buffer_capacity, model)
    trainer = instantiate(cfg.world_model.trainer)
    if settings.background_fit:
        check_background_fit(trainer)
    return WorldModelParts(model, trainer, buffer, imagination)


def make_trpo_learner(cfg: DictConfig, observation_dim: int, action_dim: int) -> TRPOLearner:
    """TRPO from ``algo``: actor and critic, the loss (GAE) and its update, the observation normaliser.
    ``algo=ppo`` builds the same learner with PPO's clipped epochs as the policy step
    (:func:`clipped_surrogate`).

    For a token policy (``policy=token_transformer|token_mlp``, on ``robot=grammar``) the sizes are
    the features per token and the padded number of tokens (:func:`probe_dimensions`); the
    normaliser is a ``TokenNorm`` whose statistics count real tokens only.
    """
    algo = cfg.algo
    if policy_architecture(cfg) in TOKEN_POLICIES:
        actor, critic = make_token_actor_critic(cfg, observation_dim, action_dim)
        normalizer, statistics = make_token_norm(observation_dim), TokenObservationStatistics(observation_dim)
        statistics_keys = (TOKENS, TOKEN_MASK)
    else:
        actor, critic = make_actor_critic(cfg, observation_dim, action_dim)
        normalizer, statistics = make_observation_norm(observation_dim), ObservationStatistics(observation_dim)
        statistics_keys = ("observation",)
    loss = TRPOLoss(actor, critic, normalize_advantage=algo.normalize_advantage, entropy_coeff=algo.entropy_coeff,
                    advantage_groups=algo.advantage_groups)
    loss.make_value_estimator(gamma=algo.gamma, lmbda=algo.lmbda)
    generator = torch.Generator().manual_seed(cfg.seed)
    ppo = algo.name == "ppo"
    updater = TRPOUpdater(
        loss, trust_region=None if ppo else make_trust_region(cfg), critic_lr=algo.critic_lr,
        critic_epochs=algo.critic_epochs, critic_minibatch_size=algo.critic_minibatch_size, generator=generator,
        clipped_step=ClippedStep(loss, actor, clipped_surrogate(cfg), generator) if ppo else None,
        critic_fit=algo.critic_fit,
    )
    return TRPOLearner(actor, critic, updater, normalizer, make_collecting_policy(normalizer, actor), statistics,
                       algo.normalizer_refresh, algo.max_consecutive_skips, statistics_keys=statistics_keys)


def make_off_policy_learner(cfg: DictConfig, observation_dim: int, action_dim: int) -> OffPolicyLearner:
    """SAC, CrossQ or REDQ from ``algo``: the tanh-Gaussian actor, TorchRL's loss, critics and replay
    buffer; on a model source, MBPO's (a model buffer beside the real one)."""
    model_based = cfg.source.kind == "model"
    if model_based:
        check_model_based_imagination(instantiate(cfg.imagination))
    actor = make_policy_actor(cfg, observation_dim, action_dim)
    normalizer = make_observation_norm(observation_dim)
    return OffPolicyLearner(off_policy_settings(cfg), actor, normalizer, make_collecting_policy(normalizer, actor),
                            ObservationStatistics(observation_dim), observation_dim, action_dim, model_based)


def make_distillation_learner(cfg: DictConfig, observation_dim: int, action_dim: int) -> DistillationLearner:
    """DAgger from ``algo.teachers`` (specialists of the training morphologies) into the token
    policy of ``cfg.policy``: the student's actor and normaliser as TRPO builds them, no critic."""
    settings = distillation_settings(cfg)
    teachers = SpecialistTeachers(morphology_env_kwargs(cfg), settings.teachers)
    actor = make_token_actor(cfg, observation_dim, action_dim)
    normalizer = make_token_norm(observation_dim)
    return DistillationLearner(settings, actor, normalizer, make_collecting_policy(normalizer, actor),
                               TokenObservationStatistics(observation_dim), teachers,
                               torch.Generator().manual_seed(cfg.seed))


# ``algo.name`` -> the factory of its learner (each takes the config and the env's sizes); the names
# are unipolicy_rl.registry's, which validation reads without importing this module.
LEARNERS: dict[str, Callable[[DictConfig, int, int], Learner]] = {
    "trpo": make_trpo_learner,
    "ppo": make_trpo_learner,
    **{name: make_off_policy_learner for name in OFF_POLICY_LEARNERS},
    "distill": make_distillation_learner,
}

# What a learner must have: the interface's attributes and methods, read off the protocol itself.
LEARNER_MEMBERS = (*Learner.__annotations__, *(name for name, member in vars(Learner).items()
                                               if callable(member) and not name.startswith("_")))


def make_learner(cfg: DictConfig, observation_dim: int, action_dim: int) -> Learner:
    """The learner ``algo.name`` names, sized for the env; one registered in :data:`LEARNERS` that
    lacks a member of the :class:`Learner` interface is refused here, before any training. With
    ``algo.policy_average.decay`` the policy that acts is an average of its weights (:class:`AveragedLearner`)."""
    check_settings(cfg, "algo.name")  # validation's rule (a direct caller may not have run validate_config)
    learner = LEARNERS[cfg.algo.name](cfg, observation_dim, action_dim)
    missing = [name for name in LEARNER_MEMBERS if not hasattr(learner, name)]
    if missing:
        raise TypeError(f"the learner of algo.name={cfg.algo.name!r} ({type(learner).__name__}) lacks "
                        f"{', '.join(missing)} of the Learner interface (unipolicy_rl.learners.Learner)")
    decay = OmegaConf.select(cfg, "algo.policy_average.decay")
    return AveragedLearner(learner, decay) if averaging(decay) else learner


def probe_dimensions(cfg: DictConfig) -> tuple[int, int]:
    """The policy's sizes for the configured robot (one robot built and closed): the flat
    observation and action sizes of the vertebrate or of a gym task, or for ``robot=grammar`` the features per
    link token ``F`` and the padded number of tokens ``L`` (one action slot per token). A
    checkpoint keeps them as ``observation_dim`` and ``action_dim``."""
    env_class, kwargs = env_builder(cfg)
    probe = env_class(1, **kwargs)
    if env_class is not MorphologyWalkerEnv:
        dims = probe.observation_spec["observation"].shape[-1], probe.action_spec.shape[-1]
    else:
        dims = tuple(probe.observation_spec[TOKENS].shape[-2:])[::-1]
    probe.close()
    return dims
