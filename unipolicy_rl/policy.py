"""The policy a run trains and a checkpoint hands over: observation normaliser, then the actor.

``policy.name`` (``conf/policy/``) chooses the architecture: ``mlp``, the flat observation
through ``algo``'s MLPs (the default, and every run before the group existed); or, for robots of
any morphology observed as padded link tokens (:mod:`unipolicy_rl.envs.tokens`),
``token_transformer``, its baseline ``token_mlp`` or ``token_modular`` (one controller shared by
every joint; :mod:`unipolicy_rl.token_networks`), built by :func:`make_token_actor_critic`
behind a :func:`make_token_norm`; ``policy.critic`` chooses the token policy's critic
(:data:`TOKEN_CRITICS`).

Kept apart from the training stack (collectors, world models, learners), so loading a policy to
run or evaluate it imports none of them.
"""

from __future__ import annotations

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs.transforms import ObservationNorm
from torchrl.modules import ValueOperator

from unipolicy_rl.networks import make_actor, make_critic, make_tanh_actor
from unipolicy_rl.token_networks import (
    make_modular_actor,
    make_padded_mlp_actor,
    make_padded_mlp_critic,
    make_pooled_token_critic,
    make_token_transformer_actor,
    make_token_transformer_critic,
)
from unipolicy_rl.token_statistics import TokenNorm

NORMALIZED_OBSERVATION = "observation_norm"
NORMALIZED_TOKENS = "tokens_norm"
# ``policy.name``: what the networks read. ``mlp`` reads the flat ``observation``; the others
# read link tokens and drive the padded, masked action of unipolicy_rl.envs.tokens.
FLAT_POLICIES = ("mlp",)
TOKEN_POLICIES = ("token_transformer", "token_mlp", "token_modular")
# ``algo.name`` of the on-policy learners, which train this module's Gaussian policies (the flat
# MLP and the token policies) with GAE and a critic fit: TRPO's natural-gradient step or PPO's
# clipped epochs. The off-policy learners build their own tanh-Gaussian actor.
ON_POLICY_ALGOS = ("trpo", "ppo")
# ``algo.name`` of every learner that trains the token policies' Gaussians: the on-policy ones, and
# ``distill``, which regresses the policy's mean on specialists' actions (the actor only, no
# critic), so a distilled policy is the same network a TRPO run can go on training.
TOKEN_POLICY_ALGOS = (*ON_POLICY_ALGOS, "distill")
# ``policy.critic`` of a token policy: the state value GAE and the critic fit use. ``transformer``:
# its own token transformer, of ``policy.critic_network``'s sizes (unset: ``policy.network``'s);
# ``pooled``: the pooled token MLP (Deep Sets) of ``algo.critic_hidden``; ``padded_mlp``: the
# padded tokens flattened through ``algo.critic_hidden`` (its weights tied to the padding).
TOKEN_CRITICS = ("transformer", "pooled", "padded_mlp")
# The critic each token policy had before ``policy.critic`` existed: a config (a checkpoint's)
# without the key builds it, so such a run resumes into the critic its weights belong to
# (token_modular came after the setting: its yaml names its critic, pooled when a config does not).
CRITIC_BEFORE_THE_SETTING = {"token_transformer": "transformer", "token_mlp": "padded_mlp"}


def policy_architecture(cfg: DictConfig) -> str:
    """``cfg.policy.name``; unknown names refused."""
    name = cfg.policy.name
    if name not in FLAT_POLICIES + TOKEN_POLICIES:
        raise ValueError(f"policy.name must be one of {FLAT_POLICIES + TOKEN_POLICIES}, got {name!r}")
    return name


def token_critic(cfg: DictConfig) -> str:
    """``cfg.policy.critic`` of a token policy (:data:`TOKEN_CRITICS`), or the critic the policy had
    before the setting existed (:data:`CRITIC_BEFORE_THE_SETTING`); unknown names refused."""
    architecture = policy_architecture(cfg)
    if architecture not in TOKEN_POLICIES:
        raise ValueError(f"policy.critic is a token policy's setting ({TOKEN_POLICIES}), not policy={architecture}'s")
    name = OmegaConf.select(cfg, "policy.critic", default=None)
    name = CRITIC_BEFORE_THE_SETTING.get(architecture, "pooled") if name is None else name
    if name not in TOKEN_CRITICS:
        raise ValueError(f"policy.critic must be one of {TOKEN_CRITICS}, got {name!r}")
    if name == "transformer" and _critic_transformer_settings(cfg) is None:
        raise ValueError(f"policy.critic=transformer takes its sizes from policy.critic_network or policy.network, "
                         f"and policy={architecture} has neither: use policy.critic=pooled or padded_mlp")
    return name


def pin_token_critic(cfg: DictConfig) -> None:
    """Writes the critic a token policy's ``cfg`` builds into ``policy.critic`` (in place).

    For a checkpoint's config from before the setting existed: merged into a newer config (as a
    resume does), the missing key would otherwise take the newer default, a critic the saved
    weights do not belong to."""
    if policy_architecture(cfg) in TOKEN_POLICIES and OmegaConf.select(cfg, "policy.critic", default=None) is None:
        OmegaConf.update(cfg, "policy.critic", token_critic(cfg), force_add=True)


def _critic_transformer_settings(cfg: DictConfig) -> DictConfig | None:
    """The transformer critic's sizes: ``policy.critic_network``, else the actor's ``policy.network``."""
    settings = OmegaConf.select(cfg, "policy.critic_network", default=None)
    return OmegaConf.select(cfg, "policy.network", default=None) if settings is None else settings


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
    """The actor ``cfg.algo`` trains, reading the normalised observation: the on-policy learners'
    Gaussian (TRPO's and PPO's; its std a free parameter), or the off-policy learners' tanh-Gaussian."""
    algo = cfg.algo
    if (architecture := policy_architecture(cfg)) != "mlp":
        raise ValueError(f"policy={architecture} reads link tokens, not a flat observation of {observation_dim}: "
                         "build it with make_token_actor_critic on an env that writes tokens (robot=grammar)")
    if algo.name in ON_POLICY_ALGOS:
        return make_actor(observation_dim, action_dim, tuple(algo.actor_hidden), algo.activation, algo.init_log_std,
                          observation_key=NORMALIZED_OBSERVATION)
    return make_tanh_actor(observation_dim, action_dim, tuple(algo.actor_hidden), algo.activation,
                           observation_key=NORMALIZED_OBSERVATION)


def make_actor_critic(cfg: DictConfig, observation_dim: int, action_dim: int):
    """The on-policy actor and state-value critic from ``cfg.algo``, both reading the normalised observation."""
    algo = cfg.algo
    actor = make_policy_actor(cfg, observation_dim, action_dim)
    critic = make_critic(observation_dim, tuple(algo.critic_hidden), algo.activation,
                         observation_key=NORMALIZED_OBSERVATION)
    return actor, critic


def make_token_norm(token_features: int, loc: torch.Tensor | None = None,
                    scale: torch.Tensor | None = None) -> TokenNorm:
    """The token policy's input normaliser: ``(tokens - loc) / scale`` per feature, padding zero;
    identity by default. Its statistics: :class:`~unipolicy_rl.token_statistics.TokenObservationStatistics`."""
    loc = torch.zeros(token_features) if loc is None else loc.clone()
    scale = torch.ones(token_features) if scale is None else scale.clone()
    return TokenNorm(loc, scale, out_key=NORMALIZED_TOKENS)


def reads_the_clock(cfg: DictConfig) -> bool:
    """Whether the policy reads the env's gait clock: where the robot has one (``robot.clock_frequency``)."""
    return OmegaConf.select(cfg, "robot.clock_frequency", default=None) is not None


def make_token_actor_critic(cfg: DictConfig, token_features: int, max_tokens: int):
    """TRPO's actor (:func:`make_token_actor`) and critic (:func:`make_token_critic`) for
    ``cfg.policy``, both reading the normalised tokens."""
    token_critic(cfg)  # a bad critic name fails before any network is built
    return make_token_actor(cfg, token_features, max_tokens), make_token_critic(cfg, token_features, max_tokens)


def make_token_actor(cfg: DictConfig, token_features: int, max_tokens: int) -> TensorDictModuleBase:
    """The Gaussian policy of ``cfg.policy`` (``token_transformer``, ``token_mlp`` or
    ``token_modular``), reading the normalised tokens, the token mask and parents, and the action mask.

    ``token_features`` (``F``) and ``max_tokens`` (``L``, the padding) come from the env's specs.
    The transformer's sizes are ``cfg.policy.network``; the padded MLP and the modular policy take
    ``algo``'s actor hidden sizes and activation; all start at ``algo.init_log_std``.
    """
    architecture = policy_architecture(cfg)
    if architecture not in TOKEN_POLICIES:
        raise ValueError(f"make_token_actor builds {TOKEN_POLICIES}, got policy={architecture}")
    algo = cfg.algo
    if algo.name not in TOKEN_POLICY_ALGOS:
        raise ValueError(f"the token policies are Gaussian policies for {' or '.join(TOKEN_POLICY_ALGOS)}, "
                         f"not for algo={algo.name}")
    if architecture == "token_transformer":
        return make_token_transformer_actor(token_features, instantiate(cfg.policy.network), algo.init_log_std,
                                            max_tokens=max_tokens, tokens_key=NORMALIZED_TOKENS)
    if architecture == "token_modular":
        return make_modular_actor(token_features, tuple(algo.actor_hidden), algo.activation, algo.init_log_std,
                                  tokens_key=NORMALIZED_TOKENS, clock=reads_the_clock(cfg))
    return make_padded_mlp_actor(token_features, max_tokens, tuple(algo.actor_hidden), algo.activation,
                                 algo.init_log_std, tokens_key=NORMALIZED_TOKENS)


def make_token_critic(cfg: DictConfig, token_features: int, max_tokens: int) -> ValueOperator:
    """The state value ``policy.critic`` names (:data:`TOKEN_CRITICS`), reading the normalised
    tokens and the token mask (the transformer's also the parents); its own weights, apart from
    the actor's, so the critic's Adam never moves the policy TRPO just bounded."""
    kind, algo = token_critic(cfg), cfg.algo
    if kind == "transformer":
        return make_token_transformer_critic(token_features, instantiate(_critic_transformer_settings(cfg)),
                                             max_tokens=max_tokens, tokens_key=NORMALIZED_TOKENS)
    if kind == "pooled":
        return make_pooled_token_critic(token_features, tuple(algo.critic_hidden), algo.activation,
                                        tokens_key=NORMALIZED_TOKENS)
    return make_padded_mlp_critic(token_features, max_tokens, tuple(algo.critic_hidden), algo.activation,
                                  tokens_key=NORMALIZED_TOKENS)
