"""Batched building blocks of the ensembles: every member's layer in one tensor, and a
standardiser with a floor on its scale.

All members run in one ``torch.baddbmm`` per layer (weights shaped ``[members, in, out]``),
so fitting 36 networks costs about what one network 36 times as wide would, never a
Python loop over networks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from unipolicy_rl.networks import ACTIVATIONS

# A feature whose spread is below this is treated as constant: dividing by ~0 would turn
# float noise into huge inputs (mbrl-lib issue 110 is that crash).
MIN_STD = 1e-6


class EnsembleLinear(nn.Module):
    """``members`` independent linear layers applied to ``[members, batch, in]`` at once."""

    def __init__(self, members: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(members, in_features, out_features))
        self.bias = nn.Parameter(torch.zeros(members, 1, out_features))
        # PyTorch's nn.Linear default, per member.
        bound = 1.0 / math.sqrt(in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class EnsembleMLP(nn.Sequential):
    """An MLP per member; input and output ``[members, batch, features]``."""

    def __init__(self, members: int, in_features: int, out_features: int, hidden: Sequence[int],
                 activation: str) -> None:
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(ACTIVATIONS)}")
        layers: list[nn.Module] = []
        width = in_features
        for size in hidden:
            layers += [EnsembleLinear(members, width, size), ACTIVATIONS[activation]()]
            width = size
        layers.append(EnsembleLinear(members, width, out_features))
        super().__init__(*layers)
        self.members = members


class Standardizer(nn.Module):
    """``(x - mean) / std`` per feature, fitted to data; std floored at :data:`MIN_STD`."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("std", torch.ones(size))

    @torch.no_grad()
    def fit(self, data: torch.Tensor) -> None:
        data = data.reshape(-1, data.shape[-1])
        self.mean.copy_(data.mean(0))
        self.std.copy_(data.std(0, correction=0).clamp_min(MIN_STD))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.std + self.mean
