"""Running mean and spread of observations, merged one epoch at a time.

The policy normalises its input with TorchRL's ``ObservationNorm``, whose ``loc`` and
``scale`` stay fixed for a whole epoch and are refreshed from these statistics between
epochs, as OpenAI baselines' TRPO did. A fixed normaliser keeps the behaviour policy one
function per epoch (what the importance ratios and the trust region assume), lets it run
inside the collector's worker processes with the policy weights, and costs a subtraction and
a division per step instead of a statistics update in every env step.

A refresh changes what the networks see, so by itself it changes the policy that runs by an
amount the trust region never bounds (the first refresh jumps from the identity to real
statistics; a coordinate at the scale floor is multiplied by up to 1/MIN_SCALE).
:func:`refresh_normalizer` therefore re-expresses the first layer of each network reading the
normalised observation in the new coordinates, so the refresh leaves every network's output
exactly as it was and only the parameterisation (what the next natural-gradient step and the
critic's Adam see) moves to the new statistics.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.envs.transforms import ObservationNorm

# A coordinate that has not varied yet (or never does) is divided by this, not by ~0.
MIN_SCALE = 1e-3
# How a refresh treats the networks behind the normaliser (config ``algo.normalizer_refresh``):
# "preserve" re-expresses their first layers so their outputs do not change; "jump" only moves
# the normaliser (OpenAI baselines' TRPO), changing the policy by an unbounded amount.
REFRESH_MODES = ("preserve", "jump")


class ObservationStatistics:
    """Count, mean and sum of squared deviations of every observation seen so far.

    Batches merge exactly (Chan et al.'s parallel update, in float64), so the result does
    not depend on how the observations were split into epochs.
    """

    def __init__(self, size: int) -> None:
        if not (isinstance(size, int) and size >= 1):
            raise ValueError(f"size must be a positive integer, got {size!r}")
        self.size = size
        self.count = 0
        self.mean = torch.zeros(size, dtype=torch.float64)
        self.squared_deviations = torch.zeros(size, dtype=torch.float64)

    def update(self, observations: torch.Tensor) -> None:
        """Merges a batch shaped ``[..., size]``."""
        if observations.shape[-1:] != (self.size,):
            raise ValueError(f"observations must end in size {self.size}, got shape {tuple(observations.shape)}")
        rows = observations.reshape(-1, self.size).to(torch.float64)
        if not torch.isfinite(rows).all():
            raise ValueError("observations must be finite")
        n = rows.shape[0]
        if n == 0:
            return
        batch_mean = rows.mean(0)
        batch_deviations = ((rows - batch_mean) ** 2).sum(0)
        total = self.count + n
        delta = batch_mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.squared_deviations = self.squared_deviations + batch_deviations + delta**2 * (self.count * n / total)
        self.count = total

    @property
    def loc(self) -> torch.Tensor:
        return self.mean.to(torch.float32)

    @property
    def scale(self) -> torch.Tensor:
        """Standard deviation (population), floored at :data:`MIN_SCALE`; ones before any data."""
        if self.count == 0:
            return torch.ones(self.size)
        return (self.squared_deviations / self.count).sqrt().clamp_min(MIN_SCALE).to(torch.float32)

    def copy_to(self, normalizer: ObservationNorm) -> None:
        """Writes ``loc`` and ``scale`` into ``normalizer`` in place (so shared copies see them)."""
        normalizer.loc.copy_(self.loc)
        normalizer.scale.copy_(self.scale)

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean.clone(), "squared_deviations": self.squared_deviations.clone()}

    def load_state_dict(self, state: dict) -> None:
        if state["mean"].shape != (self.size,):
            raise ValueError(f"statistics are for size {tuple(state['mean'].shape)}, expected ({self.size},)")
        self.count = int(state["count"])
        self.mean = state["mean"].to(torch.float64).clone()
        self.squared_deviations = state["squared_deviations"].to(torch.float64).clone()


def refresh_normalizer(statistics: ObservationStatistics, normalizer: ObservationNorm,
                       networks: tuple[nn.Module, ...] = (), mode: str = "preserve") -> None:
    """Moves ``normalizer`` to the current ``statistics``; with ``mode="preserve"`` each of
    ``networks`` (whose first ``nn.Linear`` reads the normalised observation) is rewritten so
    its output on any raw observation stays the same.

    With ``z = W (o - m0) / s0 + b`` before and ``(m1, s1)`` the new statistics, the same ``z``
    is ``W' (o - m1) / s1 + b'`` for ``W' = W diag(s1 / s0)`` and ``b' = b + W (m1 - m0) / s0``.
    """
    if mode not in REFRESH_MODES:
        raise ValueError(f"normalizer_refresh must be one of {REFRESH_MODES}, got {mode!r}")
    old_loc, old_scale = normalizer.loc.detach().clone(), normalizer.scale.detach().clone()
    statistics.copy_to(normalizer)
    if mode == "jump":
        return
    reexpress_networks(networks, old_loc, old_scale, normalizer.loc.detach(), normalizer.scale.detach())


def reexpress_networks(networks: tuple[nn.Module, ...], old_loc: torch.Tensor, old_scale: torch.Tensor,
                       new_loc: torch.Tensor, new_scale: torch.Tensor) -> None:
    """Rewrites each of ``networks``, which read ``(o - old_loc) / old_scale``, in place to give the same
    output on ``(o - new_loc) / new_scale``: what a ``preserve`` refresh does to the networks behind the
    normaliser (and to any other network reading it, such as a policy average's actor)."""
    for network in networks:
        reader = _input_reader(network)
        if isinstance(reader, nn.Linear):
            reexpress_linear(reader, old_loc, old_scale, new_loc, new_scale)
        else:
            reader.reexpress_input(old_loc, old_scale, new_loc, new_scale)


def reexpress_linear(layer: nn.Linear, old_loc: torch.Tensor, old_scale: torch.Tensor, new_loc: torch.Tensor,
                     new_scale: torch.Tensor) -> None:
    """Rewrites ``layer``, which reads ``(o - old_loc) / old_scale``, to give the same output on
    ``(o - new_loc) / new_scale``: ``W' = W diag(s1 / s0)``, ``b' = b + W (m1 - m0) / s0``."""
    if layer.in_features != old_loc.numel():
        raise ValueError(f"the first layer reads {layer.in_features} inputs, the normaliser {old_loc.numel()}")
    reexpress_weights(layer.weight, layer.bias, old_loc, old_scale, new_loc, new_scale)


def reexpress_weights(weight: torch.Tensor, bias: torch.Tensor | None, old_loc: torch.Tensor,
                      old_scale: torch.Tensor, new_loc: torch.Tensor, new_scale: torch.Tensor) -> None:
    """:func:`reexpress_linear` on the tensors of a linear map, in place: ``weight`` ``[..., out, in]``
    (leading dimensions: stacked copies, as TorchRL's losses keep their critics) whose first
    ``old_loc.numel()`` input columns read the normalised observation (a critic reads the action
    after it, which stays as it is)."""
    size = old_loc.numel()
    if weight.shape[-1] < size:
        raise ValueError(f"the layer reads {weight.shape[-1]} inputs, fewer than the normaliser's {size}")
    with torch.no_grad():
        columns = weight[..., :size].double()
        shift = ((new_loc - old_loc) / old_scale).double()
        if bias is not None:
            bias.add_((columns @ shift).to(bias.dtype))
        weight[..., :size] = (columns * (new_scale / old_scale).double()).to(weight.dtype)


def reexpress_running_statistics(running_mean: torch.Tensor, running_var: torch.Tensor, old_loc: torch.Tensor,
                                 old_scale: torch.Tensor, new_loc: torch.Tensor, new_scale: torch.Tensor) -> None:
    """Rewrites a batch (re)normalisation layer's running statistics of its first ``old_loc.numel()``
    inputs, in place, for inputs read as ``(o - new_loc) / new_scale`` instead of ``(o - old_loc) /
    old_scale``. The new input is ``a x + b`` of the old, ``a = s0 / s1``, ``b = (m0 - m1) / s1``,
    so the running mean becomes ``a mu + b`` and the variance ``a^2 var``: the layer's output in
    evaluation mode, and its renormalisation corrections in training (a batch's own statistics
    move with its inputs), stay the same."""
    size = old_loc.numel()
    with torch.no_grad():
        a = (old_scale / new_scale).double()
        b = ((old_loc - new_loc) / new_scale).double()
        running_mean[..., :size] = (running_mean[..., :size].double() * a + b).to(running_mean.dtype)
        running_var[..., :size] = (running_var[..., :size].double() * a ** 2).to(running_var.dtype)


def _input_reader(network: nn.Module):
    """What reads the normalised input in ``network``: the first submodule that says how to
    re-express itself (``reexpress_input(old_loc, old_scale, new_loc, new_scale)``, as the token
    networks of :mod:`unipolicy_rl.token_networks` do), else its first ``nn.Linear``."""
    for module in network.modules():
        if hasattr(module, "reexpress_input") or isinstance(module, nn.Linear):
            return module
    raise ValueError(f"{type(network).__name__} has no nn.Linear layer to re-express")
