"""TRPO as a TorchRL loss module.

TorchRL ships PPO variants but no TRPO. This module supplies the *loss* half of TRPO in the
shape TorchRL users expect (modelled on ``torchrl.objectives.KLPENPPOLoss``): configurable
tensordict keys through ``set_keys``, a default GAE value estimator built by
``make_value_estimator``, and actor/critic parameters held functionally in
``actor_network_params`` / ``critic_network_params``.

TRPO is not trained by back-propagating ``loss_objective`` with a first-order optimiser: the
policy moves by one natural-gradient step per batch (see
:mod:`unipolicy_rl.objectives.natural_gradient`; :mod:`unipolicy_rl.objectives.updater` adds the
critic fit), which uses the building blocks exposed here
(:meth:`TRPOLoss.advantage`, :meth:`TRPOLoss.policy_distribution_params`,
:meth:`TRPOLoss.objective`, :meth:`TRPOLoss.mean_kl`). ``forward`` reports the same
quantities as a TensorDict so the loss can be logged, tested and composed like any TorchRL loss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import (
    ProbabilisticTensorDictSequential,
    TensorDictModule,
)
from tensordict.utils import NestedKey
from torch import distributions as D
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators, dispatch_value_estimator

__all__ = ["TRPOLoss"]


class TRPOLoss(LossModule):
    """Surrogate advantage, KL to the behaviour policy and critic loss for TRPO.

    Args:
        actor_network: a probabilistic actor (e.g. :func:`unipolicy_rl.networks.make_actor`)
            whose distribution parameters (``loc``/``scale``) are written to the collected
            data, so the behaviour policy can be rebuilt for the KL.
        critic_network: a state-value operator (e.g. :func:`unipolicy_rl.networks.make_critic`).

    Keyword Args:
        critic_coeff: multiplier of the critic's mean-squared error. Defaults to ``1.0``.
        normalize_advantage: standardise advantages over the batch (zero mean, unit std)
            before they weight the ratio. Defaults to ``True``: it makes the trust-region
            step independent of the reward scale.
        advantage_eps: added to the advantage std so a constant advantage does not divide by
            zero. Defaults to ``1e-8``.
        advantage_groups: a batch key whose integer values group the samples (e.g.
            ``"morphology"``): the advantages are then standardised within each group rather
            than over the whole batch. Defaults to ``None`` (the whole batch). For robots of
            many builds in one batch: over the batch, the robots whose returns vary most
            carry the step and the trust region's KL budget, the others barely move (the
            multi-task reward-scale problem PopArt addresses); within each group every build
            pulls with the same weight. A group of one sample is centred to 0.
        entropy_coeff: weight of the mean policy entropy added to the surrogate the step
            improves (TorchRL's PPO losses call it the same). Defaults to ``0.0``, TRPO as
            published. Every step sits at the trust region's edge and shrinks the policy's
            std a little, and the KL charges a move of the mean by its size in units of the
            std: with a small std each step moves the mean less. A positive weight holds the
            std up against that fall.

    ``forward(tensordict)`` returns a TensorDict with

    * ``loss_objective``: ``-mean(ratio * A)``, ratio = ``exp(log_prob - stored log_prob)``,
      the negative surrogate advantage (the quantity TRPO's step improves);
    * ``loss_critic``: ``critic_coeff * mean((V(s) - value_target)^2)``;
    * ``kl``: mean ``KL(old || new)``, the old policy rebuilt from the stored ``loc``/``scale``
      (detached; for logging and for checking the trust region);
    * ``entropy``: mean policy entropy (detached; for logging);
    * ``loss_entropy``: ``-entropy_coeff * entropy`` (differentiable), the bonus's part of the
      objective (0 with the default ``entropy_coeff``).

    When the input has no advantage entry, the value estimator (GAE with gamma 0.99 and
    lambda 0.95 unless :meth:`make_value_estimator` says otherwise) fills it in first.

    Example:
        >>> from unipolicy_rl.networks import make_actor, make_critic
        >>> loss = TRPOLoss(make_actor(18, 4), make_critic(18))
        >>> loss.make_value_estimator(gamma=0.99, lmbda=0.97)
        >>> loss.compute_advantage(batch)   # writes "advantage" and "value_target" into batch
        >>> out = loss(batch)               # loss_objective, loss_critic, kl, entropy
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys the loss reads, configurable with ``set_keys(name=key)``.

        Attributes:
            advantage: where the advantage is read (and written by the value estimator).
            value_target: where the critic's regression target is read (and written).
            value: the critic's output key.
            sample_log_prob: log-probability of the action under the behaviour policy,
                stored at collection time (``"action_log_prob"`` in TorchRL 0.14).
            action: the action taken.
            reward: the reward key (under ``"next"``), for the value estimator.
            done: the done key (under ``"next"``), for the value estimator.
            terminated: the terminated key (under ``"next"``), for the value estimator.
        """

        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"
        value: NestedKey = "state_value"
        sample_log_prob: NestedKey = "action_log_prob"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE
    SUPPORTED_VALUE_ESTIMATORS = (
        ValueEstimators.TD0,
        ValueEstimators.TD1,
        ValueEstimators.TDLambda,
        ValueEstimators.GAE,
    )

    actor_network: ProbabilisticTensorDictSequential
    critic_network: TensorDictModule
    actor_network_params: TensorDictParams
    critic_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_critic_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        *,
        critic_coeff: float = 1.0,
        normalize_advantage: bool = True,
        advantage_eps: float = 1e-8,
        entropy_coeff: float = 0.0,
        advantage_groups: NestedKey | None = None,
    ) -> None:
        if isinstance(entropy_coeff, bool) or not (isinstance(entropy_coeff, (int, float))
                                                   and math.isfinite(entropy_coeff) and entropy_coeff >= 0):
            raise ValueError(f"entropy_coeff must be a finite number >= 0, got {entropy_coeff!r}")
        self._in_keys = None
        super().__init__()
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(critic_network, "critic_network")
        device = next(iter(self.parameters())).device
        self.register_coeff_buffer("critic_coeff", critic_coeff, device=device)
        self.normalize_advantage = normalize_advantage
        self.advantage_eps = advantage_eps
        self.advantage_groups = advantage_groups
        self.entropy_coeff = float(entropy_coeff)
        # Read the actor's own action / log-prob keys so a renamed actor needs no set_keys.
        log_prob_keys = getattr(actor_network, "log_prob_keys", None)
        sample_keys = getattr(actor_network, "dist_sample_keys", None)
        if log_prob_keys and sample_keys and len(log_prob_keys) == 1:
            self.set_keys(sample_log_prob=log_prob_keys[0], action=sample_keys[0])

    # ------------------------------------------------------------------ keys
    def _set_in_keys(self) -> None:
        keys = set(self.actor_network.in_keys) | set(self.critic_network.in_keys)
        keys |= {_under_next(key) for key in self.critic_network.in_keys}  # for GAE's next value
        keys |= set(self.actor_network.dist_params_keys)
        keys |= {self.tensor_keys.action, self.tensor_keys.sample_log_prob}
        if self.advantage_groups is not None:
            keys.add(self.advantage_groups)
        for name in ("reward", "done", "terminated"):
            keys.add(_under_next(getattr(self.tensor_keys, name)))
        self._in_keys = sorted(keys, key=str)

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @property
    def out_keys(self) -> list[str]:
        return ["loss_objective", "loss_critic", "kl", "entropy", "loss_entropy"]

    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams):
        """Build the advantage estimator (GAE, gamma 0.99, lambda 0.95 by default).

        The critic is called on the states and the next states in a loop of two rather than
        under ``vmap`` (TorchRL's ``deactivate_vmap``, set unless given): a critic whose shapes
        depend on its input, as the token transformer's that cuts the padding no robot of the
        batch uses, cannot run under ``vmap``; two calls cost what the one batched call did.
        """
        hyperparams.setdefault("deactivate_vmap", True)
        value_type, hp = self._prepare_value_estimator_kwargs(value_type, **hyperparams)
        if value_type is None:  # an estimator instance or class was given and installed
            return self
        dispatch_value_estimator(
            self,
            value_type,
            supported=self.SUPPORTED_VALUE_ESTIMATORS,
            tensor_keys={
                name: getattr(self.tensor_keys, name)
                for name in ("advantage", "value_target", "value", "reward", "done", "terminated")
            },
            **hp,
        )
        return self

    # ------------------------------------------------------------ advantage
    @torch.no_grad()
    def compute_advantage(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run the value estimator in place: writes the advantage and value-target keys.

        Uses a detached copy of the critic parameters: the advantage is data for the policy
        step and the critic's regression target, never something to differentiate.
        """
        self.value_estimator(
            tensordict,
            params=self.critic_network_params.detach(),
            target_params=self.target_critic_network_params,
        )
        return tensordict

    def advantage(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The advantage shaped like the batch, detached, standardised if configured.

        Runs the value estimator first when the advantage key is missing. With a batch of one
        sample the standard deviation is undefined (NaN), so a single advantage is passed
        through unnormalised instead of becoming NaN or zero. With ``advantage_groups`` the
        standardisation runs within each group of the batch instead.
        """
        advantage = tensordict.get(self.tensor_keys.advantage, None)
        if advantage is None:
            self.compute_advantage(tensordict)
            advantage = tensordict.get(self.tensor_keys.advantage)
        advantage = _as_batch_shaped(advantage.detach(), tensordict.batch_size, "advantage")
        if self.normalize_advantage and self.advantage_groups is not None:
            groups = tensordict.get(self.advantage_groups, None)
            if groups is None:
                raise KeyError(f"{type(self).__name__} standardises advantages within the groups of "
                               f"{self.advantage_groups}, which the batch does not have (its keys: "
                               f"{', '.join(sorted(map(str, tensordict.keys())))})")
            groups = _as_batch_shaped(groups, tensordict.batch_size, str(self.advantage_groups))
            return _standardised_within_groups(advantage, groups, self.advantage_eps)
        if self.normalize_advantage and advantage.numel() > 1:
            advantage = (advantage - advantage.mean()) / (advantage.std() + self.advantage_eps)
        return advantage

    # ---------------------------------------------------------- distributions
    def actor_parameters(self) -> list[torch.Tensor]:
        """Every trainable tensor of the policy, log-std included, in a fixed order."""
        return [p for p in self.actor_network_params.values(True, True) if p.requires_grad]

    def critic_parameters(self) -> list[torch.Tensor]:
        """Every trainable tensor of the critic, in a fixed order."""
        return [p for p in self.critic_network_params.values(True, True) if p.requires_grad]

    def policy_distribution_params(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Distribution parameters (e.g. ``loc``/``scale``) under the current actor parameters.

        Computed into a fresh TensorDict holding only the actor's inputs, so the behaviour
        policy's ``loc``/``scale`` stored in ``tensordict`` are never overwritten. Gradients
        flow to :meth:`actor_parameters`.
        """
        inputs = tensordict.select(*self.actor_network.in_keys)
        with self.actor_network_params.to_module(self.actor_network):
            return self.actor_network.get_dist_params(inputs)

    def distribution_from_params(self, params: TensorDictBase) -> D.Distribution:
        """The policy distribution built from a TensorDict of its parameters."""
        return self.actor_network.build_dist_from_params(params)

    def policy_distribution(self, tensordict: TensorDictBase) -> D.Distribution:
        """The current policy's distribution on ``tensordict`` (differentiable)."""
        return self.distribution_from_params(self.policy_distribution_params(tensordict))

    def behaviour_distribution(self, tensordict: TensorDictBase) -> D.Distribution:
        """The policy that collected the data, rebuilt from the stored ``loc``/``scale``."""
        try:
            return self.actor_network.build_dist_from_params(tensordict)
        except KeyError as err:
            raise KeyError(
                f"{type(self).__name__} needs the behaviour policy's distribution parameters "
                f"{self.actor_network.dist_params_keys} in the batch; collect with an actor "
                "that writes them (e.g. unipolicy_rl.networks.make_actor)."
            ) from err

    # ------------------------------------------------------------ objectives
    def log_prob(self, distribution: D.Distribution, tensordict: TensorDictBase) -> torch.Tensor:
        """Log-probability of the stored actions, one value per sample."""
        log_prob = distribution.log_prob(_require(tensordict, self.tensor_keys.action, "action"))
        return _as_batch_shaped(log_prob, tensordict.batch_size, "log_prob")

    def surrogate_advantage(
        self,
        distribution: D.Distribution,
        tensordict: TensorDictBase,
        advantage: torch.Tensor,
    ) -> torch.Tensor:
        """``mean(exp(log_prob - stored log_prob) * advantage)``, the quantity TRPO improves."""
        return self.surrogate_terms(distribution, tensordict, advantage).mean()

    def surrogate_terms(
        self,
        distribution: D.Distribution,
        tensordict: TensorDictBase,
        advantage: torch.Tensor,
    ) -> torch.Tensor:
        """Each sample's ``exp(log_prob - stored log_prob) * advantage``: the surrogate's terms."""
        stored_log_prob = _as_batch_shaped(
            _require(tensordict, self.tensor_keys.sample_log_prob, "behaviour log-prob").detach(),
            tensordict.batch_size,
            "stored log_prob",
        )
        ratio = torch.exp(self.log_prob(distribution, tensordict) - stored_log_prob)
        return ratio * advantage

    def objective(
        self,
        distribution: D.Distribution,
        tensordict: TensorDictBase,
        advantage: torch.Tensor,
    ) -> torch.Tensor:
        """What TRPO's step improves: the surrogate advantage, plus ``entropy_coeff`` times the
        mean policy entropy where that is set (with 0 the surrogate itself, bit for bit)."""
        surrogate = self.surrogate_advantage(distribution, tensordict, advantage)
        if self.entropy_coeff == 0.0:
            return surrogate
        return surrogate + self.entropy_coeff * distribution.entropy().mean()

    @staticmethod
    def mean_kl(old: D.Distribution, new: D.Distribution) -> torch.Tensor:
        """Mean over the batch of ``KL(old || new)`` (summed over action dimensions).

        Padded actions need nothing here: a :class:`~unipolicy_rl.masked_normal.MaskedIndependentNormal`
        policy's KL, log-probability and entropy already count its real joints only.
        """
        kl = D.kl_divergence(old, new)
        batch_dims = len(old.batch_shape)
        if kl.dim() > batch_dims:  # a factorised Normal reports one KL per action dim
            kl = kl.sum(dim=tuple(range(batch_dims, kl.dim())))
        return kl.mean()

    def critic_loss(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``critic_coeff * mean((V(s) - value_target)^2)`` under the current critic."""
        target = tensordict.get(self.tensor_keys.value_target, None)
        if target is None:
            raise KeyError(
                f"the value target {self.tensor_keys.value_target!r} is missing; run "
                "compute_advantage(batch) (or any TorchRL value estimator) first."
            )
        inputs = tensordict.select(*self.critic_network.in_keys)
        with self.critic_network_params.to_module(self.critic_network):
            value = self.critic_network(inputs).get(self.tensor_keys.value)
        return self.critic_coeff * torch.nn.functional.mse_loss(value, target.reshape(value.shape))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = tensordict.copy()  # the value estimator may add keys: keep them local
        advantage = self.advantage(tensordict)
        distribution = self.policy_distribution(tensordict)
        surrogate = self.surrogate_advantage(distribution, tensordict, advantage)
        entropy = distribution.entropy().mean()
        with torch.no_grad():
            kl = self.mean_kl(self.behaviour_distribution(tensordict), distribution)
        return TensorDict(
            {
                "loss_objective": -surrogate,
                "loss_critic": self.critic_loss(tensordict),
                "kl": kl,
                "entropy": entropy.detach(),
                "loss_entropy": -self.entropy_coeff * entropy,
            },
            batch_size=[],
        )


def _under_next(key: NestedKey) -> tuple[str, ...]:
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def _require(tensordict: TensorDictBase, key: NestedKey, what: str) -> torch.Tensor:
    """``tensordict[key]``, or a KeyError that names the key (``get`` returns None here)."""
    value = tensordict.get(key, None)
    if value is None:
        raise KeyError(
            f"the {what} key {key!r} is not in the batch; rename it with "
            "TRPOLoss.set_keys(...) if your data uses another name"
        )
    return value


def _standardised_within_groups(advantage: torch.Tensor, groups: torch.Tensor, eps: float) -> torch.Tensor:
    """Zero mean and unit std within each group of equal ``groups`` values (a group of one: 0)."""
    standardised = torch.empty_like(advantage)
    for group in groups.unique():
        members = groups == group
        values = advantage[members]
        centred = values - values.mean()
        standardised[members] = centred / (values.std() + eps) if values.numel() > 1 else centred
    return standardised


def _as_batch_shaped(value: torch.Tensor, batch_size: torch.Size, name: str) -> torch.Tensor:
    """Bring a per-sample quantity to the batch shape (GAE writes ``[*B, 1]``)."""
    if value.shape == batch_size:
        return value
    if value.shape[: len(batch_size)] == batch_size and value.numel() == batch_size.numel():
        return value.reshape(batch_size)
    raise ValueError(
        f"{name} has shape {tuple(value.shape)}, expected one value per sample of a batch of shape {tuple(batch_size)}"
    )
