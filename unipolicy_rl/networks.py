"""Policy and value networks for TRPO, built as TorchRL modules.

Both factories return ordinary TorchRL operators (``ProbabilisticActor``, ``ValueOperator``)
so that collectors, value estimators and :class:`~unipolicy_rl.objectives.TRPOLoss` can use
them without adapters. The defaults (64x64 tanh, orthogonal initialisation, state-independent
log-std starting at 0) are the ones used by stable-baselines3 and CleanRL for on-policy
continuous control, so results are comparable with theirs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict.nn import AddStateIndependentNormalScale, NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import BatchRenorm1d, IndependentNormal, ProbabilisticActor, TanhNormal, ValueOperator

__all__ = ["ACTIVATIONS", "WarmedUpBatchRenorm1d", "make_actor", "make_critic", "make_mlp", "make_q_network",
           "make_tanh_actor"]

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "silu": nn.SiLU,
}


def make_mlp(
    in_features: int,
    out_features: int,
    hidden_sizes: Sequence[int] = (64, 64),
    activation: str = "tanh",
    output_gain: float = 1.0,
) -> nn.Sequential:
    """A plain ``nn.Sequential`` MLP with orthogonal initialisation.

    Hidden layers use gain sqrt(2) and zero bias (the PPO/TRPO "implementation details" that
    keep early activations in tanh's linear range); the output layer takes ``output_gain``
    so the policy can start near a zero mean (small gain) while the critic keeps full scale.
    An empty ``hidden_sizes`` gives a single linear layer (a linear policy).
    """
    try:
        activation_class = ACTIVATIONS[activation]
    except KeyError as err:
        raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(ACTIVATIONS)}") from err
    layers: list[nn.Module] = []
    width = in_features
    for hidden in hidden_sizes:
        layers += [_orthogonal_linear(width, hidden, gain=math.sqrt(2.0)), activation_class()]
        width = hidden
    layers.append(_orthogonal_linear(width, out_features, gain=output_gain))
    return nn.Sequential(*layers)


def make_actor(
    observation_dim: int,
    action_dim: int,
    hidden_sizes: Sequence[int] = (64, 64),
    activation: str = "tanh",
    init_log_std: float = 0.0,
    *,
    observation_key: str = "observation",
    action_spec: TensorSpec | None = None,
) -> ProbabilisticActor:
    """Gaussian policy ``observation -> (loc, scale) -> action`` with a state-independent std.

    Why this shape:

    * The log-std is a free parameter vector (``AddStateIndependentNormalScale``), not a network
      output. It is a real ``nn.Parameter`` of the actor, so TRPO's natural-gradient step moves
      it together with the mean (a known TRPO bug is a log-std that silently stays out of the
      optimised parameters).
    * ``IndependentNormal`` (untransformed Gaussian, no tanh squashing) keeps the KL between
      policies analytic, which TRPO's Fisher-vector product and trust-region check rely on.
      The environment clips actions to its bounds.
    * ``return_log_prob=True`` stores ``action_log_prob`` and the ``loc``/``scale`` of the
      behaviour policy in every collected step; the loss needs both (importance ratio and the
      KL to the old policy).
    * ``init_log_std=0`` (std 1) matches stable-baselines3 and CleanRL defaults.
    * Exploration is on by default (actions are sampled); evaluate deterministically (the
      mean) under ``torchrl.envs.utils.set_exploration_type(ExplorationType.DETERMINISTIC)``.
    """
    mean_network = make_mlp(observation_dim, action_dim, hidden_sizes, activation, output_gain=0.01)
    log_std = AddStateIndependentNormalScale(action_dim, scale_mapping="exp", init_value=init_log_std)
    parameters_module = TensorDictModule(
        nn.Sequential(mean_network, log_std),
        in_keys=[observation_key],
        out_keys=["loc", "scale"],
    )
    return ProbabilisticActor(
        parameters_module,
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )


def make_critic(
    observation_dim: int,
    hidden_sizes: Sequence[int] = (64, 64),
    activation: str = "tanh",
    *,
    observation_key: str = "observation",
) -> ValueOperator:
    """State-value network ``observation -> state_value`` for GAE and the critic loss.

    Kept separate from the actor (no shared trunk) so the critic's Adam updates cannot move the
    policy outside the trust region TRPO just enforced.
    """
    return ValueOperator(
        make_mlp(observation_dim, 1, hidden_sizes, activation, output_gain=1.0),
        in_keys=[observation_key],
    )


def make_tanh_actor(
    observation_dim: int,
    action_dim: int,
    hidden_sizes: Sequence[int] = (256, 256),
    activation: str = "relu",
    *,
    observation_key: str = "observation",
) -> ProbabilisticActor:
    """Tanh-Gaussian policy ``observation -> (loc, scale) -> tanh(sample)`` in ``[-1, 1]``, for SAC-style learners.

    The network outputs the mean and the (softplus-mapped) std of a Gaussian per action; the
    sample is squashed by tanh into the env's bounds, and its log-probability carries the
    change-of-variables term (TorchRL's ``TanhNormal``). The deterministic action, for
    evaluation, is ``tanh(loc)``.
    """
    network = nn.Sequential(make_mlp(observation_dim, 2 * action_dim, hidden_sizes, activation, output_gain=0.01),
                            NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(network, in_keys=[observation_key], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )


class WarmedUpBatchRenorm1d(BatchRenorm1d):
    """TorchRL's ``BatchRenorm1d`` whose warm-up ends at ``warmup_steps`` and stays ended.

    TorchRL's layer scales its renormalisation corrections ``r`` and ``d`` by
    ``num_batches_tracked // warmup_steps``, meaning 0 during the warm-up and 1 after it, but it
    never stops counting (its ``clamp_max`` is not in place). So the factor becomes 2 after twice
    the warm-up, 3 after three times, and so on: ``r`` and ``d`` grow past their clamps
    (``max_r``, ``max_d``) and a CrossQ critic that ran well for 20,000 steps is normalised wrongly
    from then on. Capping the count in place after each training pass keeps the factor at 1.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = super().forward(x)
        if self.training:
            # clamp then copy_: both have vmap batching rules (the critics run under vmap), clamp_ has not
            self.num_batches_tracked.copy_(self.num_batches_tracked.clamp(max=self.warmup_steps))
        return out


def make_q_network(
    observation_dim: int,
    action_dim: int,
    hidden_sizes: Sequence[int] = (256, 256),
    activation: str = "relu",
    batch_renorm: bool = False,
    *,
    observation_key: str = "observation",
    batch_renorm_warmup: int = 10_000,
) -> ValueOperator:
    """Action-value network ``(observation, action) -> state_action_value``.

    ``batch_renorm`` puts batch renormalisation (:class:`WarmedUpBatchRenorm1d`) after the input
    and every hidden layer, as CrossQ does so that it can drop the target network; its
    corrections start after ``batch_renorm_warmup`` training batches (plain batch normalisation
    before; TorchRL's default 10,000, the CrossQ reference implementations' 100,000).
    """
    try:
        activation_class = ACTIVATIONS[activation]
    except KeyError as err:
        raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(ACTIVATIONS)}") from err

    def renormalisation(width: int) -> list[nn.Module]:
        return [WarmedUpBatchRenorm1d(width, warmup_steps=batch_renorm_warmup)] if batch_renorm else []

    layers: list[nn.Module] = renormalisation(observation_dim + action_dim)
    width = observation_dim + action_dim
    for hidden in hidden_sizes:
        layers += [nn.Linear(width, hidden), *renormalisation(hidden), activation_class()]
        width = hidden
    layers.append(nn.Linear(width, 1))
    return ValueOperator(_Concatenated(nn.Sequential(*layers)), in_keys=[observation_key, "action"],
                         out_keys=["state_action_value"])


class _Concatenated(nn.Module):
    """Applies ``network`` to its inputs concatenated on the last dimension."""

    def __init__(self, network: nn.Module) -> None:
        super().__init__()
        self.network = network

    def forward(self, *inputs):
        return self.network(torch.cat(inputs, dim=-1))


def _orthogonal_linear(in_features: int, out_features: int, gain: float) -> nn.Linear:
    layer = nn.Linear(in_features, out_features)
    nn.init.orthogonal_(layer.weight, gain=gain)
    nn.init.zeros_(layer.bias)
    return layer
