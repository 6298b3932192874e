"""Off-policy actor-critic learners (SAC, CrossQ, REDQ) as :class:`~unipolicy_rl.learners.Learner`s.

TorchRL ships the losses (``SACLoss``, ``CrossQLoss``, ``REDQLoss``) and the target-network
updater (``SoftUpdate``); this module adds what our loop needs around them: a TorchRL replay
buffer that keeps every real transition the learner is given, ``updates_per_step`` gradient
steps per new transition (the update-to-data ratio, UTD), the observation normaliser of the
project's policy (frozen within an epoch, refreshed between), and one state to checkpoint.

On a world model the same learner is MBPO (Janner et al. 2019): a second replay buffer keeps the
model's branches, and each minibatch draws ``real_data_share`` of its transitions from the real
buffer, the rest from the model's. The gradient steps a real batch earns (UTD x its transitions)
are then taken when the epoch's imagined batch arrives, so they see the branches of the model
fitted on that real data, as MBPO's steps follow its rollouts.

Or the learner learns while the epoch is collected (``update_every``): the collector hands it each
chunk of that many env steps as it comes (:meth:`OffPolicyLearner.update_chunk`), and it takes the
chunk's gradient steps at once, so the policy that collects moves every few steps, as in SAC's and
MBPO's own code (one env step, then its updates). Taken once per epoch instead, 1,000 real steps
then 10,000 updates at ten per step, the steps see no data of the policy they move to for a whole
epoch. On a world model, a chunk's steps mix its real data with the latest fit's branches.

Transitions are stored with their raw observations and normalised when a minibatch is drawn,
with the current statistics: an old transition is seen the way the current policy would see it.
How a refresh treats the networks is ``normalizer_refresh``: ``jump`` only moves the normaliser,
so the actor and every critic compute another function of the raw observation from then on;
``preserve`` re-expresses what first reads the normalised observation in the new coordinates,
as TRPO's refresh does: the actor's first linear layer, and in every critic (online and target,
stacked as TorchRL's loss keeps them) the observation's columns of its first linear layer or,
with batch renormalisation (CrossQ), its input layer's running statistics. The action's columns
stay as they are. The effect on the policy is logged as the KL between the squashed Gaussians
before and after (tanh is a bijection, so that KL is the one of the Gaussians under it): 0 to
float precision with ``preserve``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.distributions import Normal, kl_divergence
from torchrl.data import Bounded, LazyTensorStorage, ReplayBuffer
from torchrl.envs.transforms import ObservationNorm
from torchrl.objectives import CrossQLoss, LossModule, REDQLoss, SACLoss, SoftUpdate

from unipolicy_rl.collectors.buffer_state import compact_state, load_compact_state
from unipolicy_rl.collectors.real import is_imagined
from unipolicy_rl.learners.base import load_policy_state, observation_probe, policy_state
from unipolicy_rl.networks import WarmedUpBatchRenorm1d, make_q_network
from unipolicy_rl.observation_statistics import (
    REFRESH_MODES,
    ObservationStatistics,
    reexpress_running_statistics,
    reexpress_weights,
    refresh_normalizer,
)
from unipolicy_rl.policy import NORMALIZED_OBSERVATION

LOSSES = ("sac", "crossq", "redq")


@dataclass(frozen=True)
class OffPolicySettings:
    """An off-policy learner's settings (``conf/algo/{sac,crossq,redq}.yaml``; the papers' values there).

    Args:
        loss: ``sac``, ``crossq`` (batch renormalisation in the critics, no target network) or
            ``redq`` (an ensemble of critics, a random subset of them in each target).
        critic_hidden, activation: each critic's MLP (the actor's is the policy's, ``algo.actor_hidden``).
        gamma: discount.
        learning_rate: Adam's step size for the actor, the critics and the entropy temperature.
        adam_betas: Adam's betas (the CrossQ paper: 0.5, 0.999; crossq.yaml keeps SAC's, see there).
        batch_size: transitions per gradient step.
        updates_per_step: gradient steps per new real transition (UTD), at least 1.
        buffer_capacity: real transitions kept (FIFO).
        learning_starts: transitions in the buffer before the first gradient step.
        num_critics: critics (SAC, CrossQ: 2; REDQ: 10).
        sampled_critics: REDQ's critics in each target (2).
        target_update_rate: Polyak rate of the target critics (SAC, REDQ: 0.005); None: no target
            network (CrossQ).
        actor_update_every: one actor and temperature step every this many critic steps (CrossQ: 3).
        batch_renorm: batch renormalisation in the critics (CrossQ).
        batch_renorm_warmup: training batches before batch renormalisation's corrections start
            (CrossQ; TorchRL's default 10,000, the CrossQ reference implementations' 100,000).
        alpha_init: the entropy temperature's start; it is learned towards ``target_entropy``.
        target_entropy: the policy's entropy target (``auto``: minus the number of actions).
        real_data_share: model-based runs (MBPO): the share of each minibatch drawn from real
            transitions, the rest from the model's branches (MBPO: 0.05).
        model_buffer_capacity: model-based runs: imagined transitions kept (FIFO: the branches of
            the latest fits, so the model data follow the latest models, as in MBPO).
        normalizer_refresh: ``jump`` (only the normaliser moves between epochs) or ``preserve``
            (the actor's and critics' first layers are re-expressed so that their outputs stay
            the same; see the module docstring).
        update_every: env steps (of each env) between rounds of gradient steps while the epoch is
            collected (SAC's and MBPO's code: 1); None: one round per epoch, after it.
    """

    loss: str = "sac"
    critic_hidden: tuple[int, ...] = (256, 256)
    activation: str = "relu"
    gamma: float = 0.99
    learning_rate: float = 3e-4
    adam_betas: tuple[float, float] = (0.9, 0.999)
    batch_size: int = 256
    updates_per_step: float = 1.0
    buffer_capacity: int = 1_000_000
    learning_starts: int = 1000
    num_critics: int = 2
    sampled_critics: int = 2
    target_update_rate: float | None = 0.005
    actor_update_every: int = 1
    batch_renorm: bool = False
    batch_renorm_warmup: int = 10_000
    alpha_init: float = 1.0
    target_entropy: float | str = "auto"
    real_data_share: float = 0.05
    model_buffer_capacity: int = 100_000
    normalizer_refresh: str = "jump"
    update_every: int | None = None

    def __post_init__(self) -> None:
        if self.normalizer_refresh not in REFRESH_MODES:
            raise ValueError(f"algo.normalizer_refresh must be one of {REFRESH_MODES}, got {self.normalizer_refresh!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"algo.loss must be one of {LOSSES}, got {self.loss!r}")
        for name in ("batch_size", "buffer_capacity", "model_buffer_capacity", "num_critics", "sampled_critics",
                     "actor_update_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"algo.{name} must be an integer >= 1, got {value!r}")
        for name in ("learning_starts", "batch_renorm_warmup"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"algo.{name} must be an integer >= 0, got {value!r}")
        if not (isinstance(self.updates_per_step, (int, float)) and self.updates_per_step >= 1):
            raise ValueError(f"algo.updates_per_step (the update-to-data ratio) must be >= 1, got "
                             f"{self.updates_per_step!r}")
        if not 0 < self.gamma <= 1:
            raise ValueError(f"algo.gamma must lie in (0, 1], got {self.gamma!r}")
        if not self.learning_rate > 0:
            raise ValueError(f"algo.learning_rate must be positive, got {self.learning_rate!r}")
        if self.target_update_rate is not None and not 0 < self.target_update_rate <= 1:
            raise ValueError(f"algo.target_update_rate must lie in (0, 1] or be null, got {self.target_update_rate!r}")
        if self.loss == "redq" and self.sampled_critics > self.num_critics:
            raise ValueError(f"algo.sampled_critics ({self.sampled_critics}) must not exceed algo.num_critics "
                             f"({self.num_critics})")
        if self.loss == "crossq" and self.target_update_rate is not None:
            raise ValueError("algo.target_update_rate must be null for crossq: CrossQ has no target network")
        if self.loss != "crossq" and self.target_update_rate is None:
            raise ValueError(f"algo.target_update_rate must be set for {self.loss}: its critics' targets need one")
        if isinstance(self.real_data_share, bool) or not (isinstance(self.real_data_share, (int, float))
                                                          and 0 <= self.real_data_share <= 1):
            raise ValueError(f"algo.real_data_share must lie in [0, 1], got {self.real_data_share!r}")
        if self.learning_starts > self.buffer_capacity:
            raise ValueError(f"algo.learning_starts ({self.learning_starts}) must not exceed algo.buffer_capacity "
                             f"({self.buffer_capacity}): the buffer never holds that many transitions, so the run "
                             f"would never take a gradient step")
        betas = self.adam_betas
        if not (isinstance(betas, (tuple, list)) and len(betas) == 2 and all(
                isinstance(beta, (int, float)) and not isinstance(beta, bool) and 0 <= beta < 1 for beta in betas)):
            raise ValueError(f"algo.adam_betas must be two numbers in [0, 1) (Adam's beta1, beta2), got {betas!r}")
        if isinstance(self.alpha_init, bool) or not (isinstance(self.alpha_init, (int, float))
                                                     and 0 < self.alpha_init < math.inf):
            raise ValueError(f"algo.alpha_init (the entropy temperature's start, learned as its log) must be a "
                             f"positive number, got {self.alpha_init!r}")
        if self.update_every is not None and (isinstance(self.update_every, bool)
                                              or not isinstance(self.update_every, int) or self.update_every < 1):
            raise ValueError(f"algo.update_every must be an integer >= 1 (env steps between rounds of gradient "
                             f"steps) or null (one round per epoch), got {self.update_every!r}")
        if not (self.target_entropy == "auto" or isinstance(self.target_entropy, (int, float))):
            raise ValueError(f"algo.target_entropy must be 'auto' or a number, got {self.target_entropy!r}")


def check_model_based_imagination(imagination) -> None:
    """Refuses, by name, an imagination an off-policy learner cannot learn MBPO's way from.

    The learner earns its gradient steps from real batches (``imagination.train_on_real``) and
    takes them on the one imagined batch that follows each fit (``stopping.kind=fixed``,
    ``max_updates=1``): ``imagination=mbpo`` is such a group. ``imagination`` is an
    :class:`~unipolicy_rl.collectors.ImaginationSettings`.
    """
    if not imagination.train_on_real:
        raise ValueError("imagination.train_on_real=false, but an off-policy learner on a world model (MBPO) needs "
                         "the real batches: they fill its real buffer and earn its gradient steps; use "
                         "imagination=mbpo")
    stopping = imagination.stopping
    if stopping.kind != "fixed" or stopping.max_updates != 1:
        raise ValueError(f"imagination.stopping (kind={stopping.kind!r}, max_updates={stopping.max_updates!r}): an "
                         f"off-policy learner on a world model takes one imagined batch per model fit "
                         f"(kind=fixed, max_updates=1; its size is imagination.steps_per_batch); use "
                         f"imagination=mbpo")


def make_loss(settings: OffPolicySettings, actor: TensorDictModuleBase, observation_dim: int,
              action_dim: int) -> LossModule:
    """TorchRL's loss ``settings.loss`` names, its critics built here, reading the normalised observation."""
    critic = make_q_network(observation_dim, action_dim, tuple(settings.critic_hidden), settings.activation,
                            settings.batch_renorm, observation_key=NORMALIZED_OBSERVATION,
                            batch_renorm_warmup=settings.batch_renorm_warmup)
    spec = Bounded(-1.0, 1.0, shape=(action_dim,))
    common = {"num_qvalue_nets": settings.num_critics, "loss_function": "l2", "alpha_init": settings.alpha_init,
              "action_spec": spec, "target_entropy": settings.target_entropy}
    if settings.loss == "sac":
        loss = SACLoss(actor, critic, delay_qvalue=True, **common)
    elif settings.loss == "crossq":
        loss = CrossQLoss(actor, critic, **common)
    else:
        loss = REDQLoss(actor, critic, sub_sample_len=settings.sampled_critics, delay_qvalue=True, **common)
    loss.make_value_estimator(gamma=settings.gamma)
    create_lazy_buffers(loss)
    return loss


# The buffers TorchRL's losses create at their first step (create_lazy_buffers makes them up front).
LAZY_BUFFERS = ("target_entropy_buffer",)


def create_lazy_buffers(loss: LossModule) -> None:
    """Creates the buffers a TorchRL loss would create at its first step, now.

    REDQLoss registers ``target_entropy_buffer`` the first time it reads its target entropy: a
    checkpoint written after a step holds it, and the fresh loss of a resume would refuse it as an
    unexpected key. The value is a constant of the settings (``auto``: minus the number of
    actions), so creating it early changes nothing the loss computes. (SACLoss and CrossQLoss
    create theirs, ``_target_entropy``, in their constructors.)
    """
    loss.target_entropy  # noqa: B018 - the property creates the buffer


def with_lazy_buffers(loss: LossModule, saved: dict) -> dict:
    """``saved`` (a loss's state dict) with the buffers :func:`create_lazy_buffers` adds taken from
    ``loss`` where ``saved`` predates them (a checkpoint written before the loss's first step)."""
    return {**{key: value for key, value in loss.state_dict().items() if key in LAZY_BUFFERS}, **saved}


class OffPolicyLearner:
    """``updates_per_step`` gradient steps of a TorchRL off-policy loss per new real transition.

    Args:
        settings: what :class:`OffPolicySettings` says.
        actor: the tanh-Gaussian actor (reads the normalised observation).
        normalizer: the policy's observation normaliser.
        policy: the collecting policy, ``normalizer`` then ``actor``.
        statistics: the observation statistics the normaliser is refreshed from.
        observation_dim, action_dim: the env's sizes.
        model_based: learn MBPO's way: real batches are stored and earn gradient steps, imagined
            batches fill the model buffer and the earned steps are taken then, on minibatches
            that mix real and model transitions (``settings.real_data_share``). Otherwise only
            real batches come, and each pays its steps at once.
    """

    def __init__(self, settings: OffPolicySettings, actor: TensorDictModuleBase, normalizer: ObservationNorm,
                 policy: TensorDictModuleBase, statistics: ObservationStatistics, observation_dim: int,
                 action_dim: int, model_based: bool = False) -> None:
        self.settings = settings
        self.actor, self.normalizer, self.policy, self.statistics = actor, normalizer, policy, statistics
        self.model_based = model_based
        self.loss = make_loss(settings, actor, observation_dim, action_dim)
        betas = tuple(settings.adam_betas)
        self.actor_optimizer = torch.optim.Adam(self.loss.actor_network_params.flatten_keys().values(),
                                                lr=settings.learning_rate, betas=betas)
        self.critic_optimizer = torch.optim.Adam(self.loss.qvalue_network_params.flatten_keys().values(),
                                                 lr=settings.learning_rate, betas=betas)
        self.alpha_optimizer = torch.optim.Adam([self.loss.log_alpha], lr=settings.learning_rate, betas=betas)
        self.target_update = (None if settings.target_update_rate is None
                              else SoftUpdate(self.loss, tau=settings.target_update_rate))
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(settings.buffer_capacity))
        self.model_buffer = (ReplayBuffer(storage=LazyTensorStorage(settings.model_buffer_capacity))
                             if model_based else None)
        self.batch_keys = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
                           ("next", "terminated"))
        self.gradient_steps = 0
        self.owed_steps = 0.0  # earned gradient steps not taken yet (a fraction, or MBPO's until model data come)
        # update_every: what this epoch's chunks brought and measured, until update() reports it
        self._chunk_transitions, self._chunk_steps, self._chunk_totals = 0, 0, {}

    # -- the Learner interface --------------------------------------------------------------
    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """A real epoch (its transitions stored, their gradient steps taken, or with ``update_every``
        only reported: they were taken as its chunks came) or a model's branches (MBPO: stored, and
        the real data's owed steps taken on them)."""
        new = batch.reshape(-1).select(*self.batch_keys).clone()
        if is_imagined(batch):
            if self.model_buffer is None:
                raise ValueError("this off-policy learner was built for real data only (model_based=False) and "
                                 "was given an imagined batch: build it with model_based=True (MBPO)")
            self.model_buffer.extend(new)
        elif self.settings.update_every is not None:
            return self._report_chunks(new.numel())
        else:
            self.buffer.extend(new)
            self.owed_steps += self.settings.updates_per_step * new.numel()
            if self.model_based:  # the steps wait for the model's branches of this epoch
                return self._progress()
        totals, steps = self._take_owed_steps()
        return {**_means(totals, steps), **self._progress()}

    def update_chunk(self, chunk: TensorDictBase) -> None:
        """``update_every``: a chunk of the epoch being collected, stored, and its gradient steps
        taken now (on a world model, on minibatches that mix it with the latest fit's branches),
        before the policy collects the next chunk. :meth:`update` on the epoch reports them."""
        if self.settings.update_every is None:
            raise ValueError("update_chunk needs algo.update_every: without it the learner takes its gradient "
                             "steps once per epoch, in update()")
        if is_imagined(chunk):
            raise ValueError("update_chunk takes real transitions as they are collected, not a model's branches")
        new = chunk.reshape(-1).select(*self.batch_keys).clone()
        self.buffer.extend(new)
        self.owed_steps += self.settings.updates_per_step * new.numel()
        totals, steps = self._take_owed_steps()
        self._chunk_transitions += new.numel()
        self._chunk_steps += steps
        for name, value in totals.items():
            self._chunk_totals[name] = self._chunk_totals.get(name, 0.0) + value

    def _report_chunks(self, transitions: int) -> dict[str, float]:
        if transitions != self._chunk_transitions:
            raise ValueError(f"algo.update_every={self.settings.update_every}: the learner takes its steps on the "
                             f"epoch's chunks as they come (update_chunk, which the real collector calls), and has "
                             f"seen {self._chunk_transitions} of this real batch's {transitions} transitions")
        metrics = _means(self._chunk_totals, self._chunk_steps)
        self._chunk_transitions, self._chunk_steps, self._chunk_totals = 0, 0, {}
        return {**metrics, **self._progress()}

    def _take_owed_steps(self) -> tuple[dict[str, float], int]:
        """The gradient steps earned so far (a fraction waits), once the buffer holds
        ``learning_starts`` transitions (steps earned before that are dropped): the sums of what
        they measured, and how many."""
        steps = int(self.owed_steps)
        self.owed_steps -= steps
        if len(self.buffer) < max(self.settings.learning_starts, 1):
            return {}, 0
        totals: dict[str, float] = {}
        for _ in range(steps):
            for name, value in self._gradient_step().items():
                totals[name] = totals.get(name, 0.0) + value
        return totals, steps

    def _progress(self) -> dict[str, float]:
        progress = {"train/gradient_steps": float(self.gradient_steps), "train/buffer_size": float(len(self.buffer))}
        if self.model_buffer is not None:
            progress["train/model_buffer_size"] = float(len(self.model_buffer))
        return progress

    def sample_minibatch(self) -> TensorDictBase:
        """``batch_size`` transitions: real ones only, or (MBPO) ``real_data_share`` of them real
        and the rest from the model buffer."""
        size = self.settings.batch_size
        if self.model_buffer is None or len(self.model_buffer) == 0:
            return self.buffer.sample(size)
        real = int(round(size * self.settings.real_data_share))
        parts = [self.buffer.sample(real)] if real else []
        if real < size:
            parts.append(self.model_buffer.sample(size - real))
        return torch.cat(parts) if len(parts) > 1 else parts[0]

    def _gradient_step(self) -> dict[str, float]:
        sample = self.sample_minibatch()
        self.normalizer(sample)
        self.normalizer(sample["next"])
        losses = self.loss(sample)
        update_actor = self.gradient_steps % self.settings.actor_update_every == 0
        total = losses["loss_qvalue"] + (losses["loss_actor"] + losses["loss_alpha"] if update_actor else 0.0)
        for optimizer in (self.critic_optimizer, self.actor_optimizer, self.alpha_optimizer):
            optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.critic_optimizer.step()
        if update_actor:
            self.actor_optimizer.step()
            self.alpha_optimizer.step()
        if self.target_update is not None:
            self.target_update.step()
        self.gradient_steps += 1
        return {"loss_critic": losses["loss_qvalue"].item(), "loss_actor": losses["loss_actor"].item(),
                "alpha": self.loss.log_alpha.detach().exp().item(),
                "entropy": float(losses.get("entropy", torch.tensor(math.nan)).detach())}

    def refresh_observation_normalizer(self, batch: TensorDictBase) -> dict[str, float]:
        observations = batch["observation"]
        probe = observation_probe(observations)
        with torch.no_grad():
            before = self._gaussian(probe)
            old_loc, old_scale = self.normalizer.loc.clone(), self.normalizer.scale.clone()
            self.statistics.update(observations)
            # TRPO's refresh for the actor (and the mode's check); the critics, stacked, below
            refresh_normalizer(self.statistics, self.normalizer, (self.actor,), self.settings.normalizer_refresh)
            if self.settings.normalizer_refresh == "preserve":
                self._reexpress_critics(old_loc, old_scale, self.normalizer.loc, self.normalizer.scale)
            after = self._gaussian(probe)
        return {"train/refresh_kl": kl_divergence(before, after).sum(-1).mean().item()}

    def _reexpress_critics(self, old_loc: torch.Tensor, old_scale: torch.Tensor, new_loc: torch.Tensor,
                           new_scale: torch.Tensor) -> None:
        """The preserving refresh of every critic's first layer, online and target (CrossQ has no
        target network: TorchRL's "target" parameters there are the online ones)."""
        key, layer = first_layer(self.loss.qvalue_network, (nn.Linear, WarmedUpBatchRenorm1d))
        targets = ("target_qvalue_network_params",) if self.target_update is not None else ()
        for name in ("qvalue_network_params", *targets):
            first = getattr(self.loss, name).get(key)
            if isinstance(layer, nn.Linear):
                reexpress_weights(first["weight"], first.get("bias", None), old_loc, old_scale, new_loc, new_scale)
            else:
                reexpress_running_statistics(first["running_mean"], first["running_var"], old_loc, old_scale,
                                             new_loc, new_scale)

    def _gaussian(self, observations: TensorDictBase) -> Normal:
        """The policy's Gaussian before its tanh, on raw observations."""
        params = self.actor.get_dist_params(self.normalizer(observations.clone()))
        return Normal(params["loc"], params["scale"])

    def policy_state(self) -> dict:
        return policy_state(self.actor, self.statistics)

    def start_from_policy(self, policy: dict) -> None:
        load_policy_state(self.actor, self.normalizer, policy)

    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "alpha_optimizer": self.alpha_optimizer.state_dict(),
            "observation_statistics": self.statistics.state_dict(),
            "buffer": compact_state(self.buffer),
            **({"model_buffer": compact_state(self.model_buffer)} if self.model_buffer is not None else {}),
            "gradient_steps": self.gradient_steps,
            "owed_steps": self.owed_steps,
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(with_lazy_buffers(self.loss, state["loss"]))
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        self.statistics.load_state_dict(state["observation_statistics"])
        self.statistics.copy_to(self.normalizer)
        load_compact_state(self.buffer, state["buffer"])
        if self.model_buffer is not None:
            load_compact_state(self.model_buffer, state["model_buffer"])
        self.gradient_steps = int(state["gradient_steps"])
        self.owed_steps = float(state["owed_steps"])

    def close(self) -> None:
        """Nothing runs beside an off-policy learner."""


def _means(totals: dict[str, float], steps: int) -> dict[str, float]:
    """Per-step means of what ``steps`` gradient steps measured, as ``train/`` metrics."""
    return {f"train/{name}": value / max(steps, 1) for name, value in totals.items()}


def first_layer(network: nn.Module, kinds: type | tuple[type, ...]) -> tuple[tuple[str, ...], nn.Module]:
    """(its key in the network's parameters, as TorchRL's losses keep them, and the layer): the first
    submodule of ``network`` of one of ``kinds``, the one that reads its input."""
    for name, module in network.named_modules():
        if isinstance(module, kinds):
            return tuple(name.split(".")), module
    raise ValueError(f"{type(network).__name__} has no {kinds} layer to re-express")
