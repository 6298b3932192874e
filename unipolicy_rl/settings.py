"""The typed settings a run's parts take, built from the Hydra config's nodes.

With :mod:`unipolicy_rl.factories` this module is a builder, a reader of the config: it turns
``algo`` into the learner's settings dataclass and ``world_model`` into the dynamics. It sits
below start-up validation (:mod:`unipolicy_rl.validation`), which builds each of these once so
their own checks run before any robot is built, and below the factories, which hand them to
the parts; neither of those two imports the other's builders through this module's back door.
"""

from __future__ import annotations

import dataclasses

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from unipolicy_rl.device import resolve_device
from unipolicy_rl.env_factories import (
    env_kind,
    env_kwargs,
    episode_length,
    frames_per_epoch,
    gym_task,
    morphology_env_kwargs,
    robot_kind,
)
from unipolicy_rl.envs import DesignDistribution
from unipolicy_rl.envs.gym_task import GYM, make_gym_env
from unipolicy_rl.learners import OffPolicySettings
from unipolicy_rl.learners.distillation import DistillationSettings
from unipolicy_rl.objectives import ClippedSurrogate, TrustRegion
from unipolicy_rl.training.progress import EvaluationPlan, MorphologyGrid
from unipolicy_rl.world_models import Dynamics, FlatLayout, StateLayout, TokenLayout
from unipolicy_rl.world_models.token_layout import TOKEN_STATE


def make_trust_region(cfg: DictConfig) -> TrustRegion:
    """TRPO's policy-step settings from ``algo`` (``conf/algo/trpo.yaml``)."""
    algo = cfg.algo
    return TrustRegion(max_kl=algo.max_kl, damping=algo.damping, cg_iters=algo.cg_iters,
                       backtrack_factor=algo.backtrack_factor, max_backtracks=algo.max_backtracks,
                       fisher_fraction=algo.fisher_fraction)


def clipped_surrogate(cfg: DictConfig) -> ClippedSurrogate:
    """PPO's policy-step settings from ``algo`` (``conf/algo/ppo.yaml``)."""
    algo = cfg.algo
    return ClippedSurrogate(epochs=algo.policy_epochs, minibatch_size=algo.policy_minibatch_size, lr=algo.policy_lr,
                            clip_epsilon=algo.clip_epsilon, max_grad_norm=algo.max_grad_norm,
                            target_kl=algo.target_kl)


def off_policy_settings(cfg: DictConfig) -> OffPolicySettings:
    """An off-policy learner's settings from ``algo`` (its ``name`` is the loss; the actor's own
    keys belong to the policy)."""
    fields = {field.name for field in dataclasses.fields(OffPolicySettings)} - {"loss"}
    algo = OmegaConf.to_container(cfg.algo, resolve=True)
    settings = {key: tuple(value) if isinstance(value, list) else value for key, value in algo.items() if key in fields}
    return OffPolicySettings(loss=cfg.algo.name, **settings)


def distillation_settings(cfg: DictConfig) -> DistillationSettings:
    """Distillation's settings from ``algo`` (``conf/algo/distill.yaml``)."""
    algo = cfg.algo
    return DistillationSettings(teachers=tuple(str(path) for path in algo.teachers), learning_rate=algo.learning_rate,
                                batch_size=algo.batch_size, updates_per_epoch=algo.updates_per_epoch,
                                buffer_capacity=algo.buffer_capacity, normalizer_refresh=algo.normalizer_refresh)


def learner_settings(cfg: DictConfig) -> TrustRegion | ClippedSurrogate | OffPolicySettings | DistillationSettings:
    """The settings of ``algo`` that check themselves, built (what validation runs at start-up)."""
    if cfg.algo.name == "trpo":
        return make_trust_region(cfg)
    if cfg.algo.name == "distill":
        return distillation_settings(cfg)
    return clipped_surrogate(cfg) if cfg.algo.name == "ppo" else off_policy_settings(cfg)


def model_layout(cfg: DictConfig) -> StateLayout | TokenLayout | FlatLayout:
    """What the world model's state holds (``world_model.model_state``): the vertebrate's
    ``full`` or ``thesis`` state for its observation, or for ``robot=grammar`` every link's
    token (``tokens``, padded to the env's ``max_links``); for ``env=gym`` the task's observation,
    read off its specs (:meth:`FlatLayout.from_env`)."""
    if env_kind(cfg) == GYM:
        env = make_gym_env(env_id=gym_task(cfg).id)
        layout = FlatLayout.from_env(env)
        env.close()
        return layout
    if cfg.world_model.model_state == TOKEN_STATE:
        if robot_kind(cfg) != "grammar":  # (validation's _world_model_reads_the_robot says more, earlier)
            raise ValueError(f"world_model.model_state={TOKEN_STATE} models link tokens, which "
                             f"robot={robot_kind(cfg)} does not write: train it with robot=grammar")
        return TokenLayout(morphology_env_kwargs(cfg)["max_links"])
    robot = cfg.robot
    return StateLayout.for_env(instantiate(robot.settings, _convert_="all"), robot.observation, robot.append_design,
                               cfg.world_model.model_state)


def make_dynamics_model(cfg: DictConfig, action_dim: int | None = None,
                        device: torch.device | str | None = None) -> Dynamics:
    """The world model's dynamics (``world_model.model``), sized for the robot and observation
    (:func:`model_layout`; ``action_dim`` by default the robot's: the vertebrate's actuated
    joints, or a grammar robot's token slots), on ``device`` (default: the config's). ``cfg``
    has a ``world_model`` (validate_config's check)."""
    layout = model_layout(cfg)
    if action_dim is None:
        if isinstance(layout, FlatLayout):
            action_dim = len(layout.action_low)
        else:
            action_dim = layout.max_links if isinstance(layout, TokenLayout) else len(cfg.robot.settings.actuated)
    heads = {}
    if env_kind(cfg) == GYM and learned_heads(cfg):  # env.reward / env.termination decide what the ensemble learns
        heads = {"learn": learned_heads(cfg)}
    # Partial, then called: Hydra would turn the layout dataclass into a config if passed through it.
    device = resolve_device(cfg.device) if device is None else torch.device(device)
    with torch.device(device):
        return instantiate(cfg.world_model.model, _partial_=True, _convert_="all")(layout=layout, action_dim=action_dim,
                                                                                  **heads)


def learned_heads(cfg: DictConfig) -> list[str]:
    """For ``env=gym``: what the world model learns beside the next state, as ``env.reward`` and
    ``env.termination`` say; a model that cannot learn them (PCE), or a ``world_model.model.learn``
    that says otherwise, is refused by name."""
    heads = gym_task(cfg).learned_heads()
    configured = list(OmegaConf.select(cfg, "world_model.model.learn", default=[]) or [])
    if configured and configured != heads:
        raise ValueError(f"world_model.model.learn={configured} disagrees with env.reward={cfg.env.reward} and "
                         f"env.termination={cfg.env.termination} (which learn {heads}): on env=gym set those two, "
                         f"not world_model.model.learn")
    if heads and "learn" not in OmegaConf.select(cfg, "world_model.model", default={}):
        raise ValueError(f"world_model.model={cfg.world_model.model._target_.rsplit('.', 1)[-1]} learns no reward or "
                         f"termination, and env.id={cfg.env.id} needs {heads} learned: use source=moe, or a known "
                         f"reward and termination (env.reward=known, env.termination=known|none)")
    return heads


def evaluation_designs(cfg: DictConfig, grid: int) -> tuple:
    """``grid`` designs per axis over the evaluation's ranges (``evaluation.length_range``, ``density_range``)."""
    evaluation = cfg.evaluation
    return tuple(DesignDistribution(tuple(evaluation.length_range), tuple(evaluation.density_range)).grid(grid))


def evaluation_plan(cfg: DictConfig) -> EvaluationPlan:
    """What the run's reports and evaluations run on (``evaluation``, the env's sizes, the seed): the
    walker's design grid (``evaluation.grid`` per axis) and its env, a grammar run's morphology grids
    (``evaluation.morphology_grid`` while training, ``evaluation.grid`` at the end), or a gym task."""
    evaluation = cfg.evaluation
    common = {"seed": cfg.seed, "epoch_steps": frames_per_epoch(cfg), "episode_length": episode_length(cfg),
              "schedule": (evaluation.every_steps, evaluation.dense_until, evaluation.then_every_steps)}
    if env_kind(cfg) == GYM:
        return EvaluationPlan(**common, gym=gym_task(cfg))
    designs = evaluation_designs(cfg, evaluation.grid)
    walker = {**common, "designs": designs, "final_episodes": evaluation.episodes,
              "control_period": cfg.robot.physics.time_step * cfg.robot.physics.substeps}
    if robot_kind(cfg) == "grammar":
        kwargs = morphology_env_kwargs(cfg, evaluation.morphologies)
        return EvaluationPlan(**walker, morphologies=MorphologyGrid(
            kwargs, evaluation_designs(cfg, evaluation.morphology_grid), cfg.seed),
            final_morphologies=MorphologyGrid(kwargs, designs, cfg.seed))
    return EvaluationPlan(**walker, env_kwargs=env_kwargs(cfg))
