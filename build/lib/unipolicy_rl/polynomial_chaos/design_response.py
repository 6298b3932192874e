"""A policy's episode over the uncertain design, as a polynomial chaos expansion in (l, rho).

With deterministic actions the physics is deterministic too, so under a trained policy every
observed coordinate at every step is a function of the design alone: two inputs, uniform over
the design box. A Legendre PCE of that function, one per (step, coordinate), is fitted by least
squares to a few dozen real episodes at Gauss-Legendre nodes of the box (rolled by
:func:`~unipolicy_rl.evaluation.policy_trajectories`), and then answers
without more physics: the mean and variance of every coordinate over time (from the
coefficients), its distribution (the expansion at any number of designs) and the episode of
any one design. This is the thesis' uncertainty quantification for a policy, where its
expansion over random actions (:class:`~unipolicy_rl.polynomial_chaos.ThesisMEPCE`) answers
it for an action distribution.

Whether two inputs and a modest order describe the policy's response is a property of the
policy (a gait that stumbles on part of the box is not smooth there): ``python -m
unipolicy_rl.uq`` measures the expansion against Monte Carlo episodes at random designs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from unipolicy_rl.polynomial_chaos.basis import UniformInputs
from unipolicy_rl.polynomial_chaos.expansion import PolynomialChaos


def gauss_legendre_designs(points: int, length_range: Sequence[float], density_range: Sequence[float]) -> torch.Tensor:
    """``[points**2, 2]`` designs (l, rho) at the tensor-product Gauss-Legendre nodes of the box.

    Nodes of a ``points``-point rule integrate polynomials up to degree ``2 points - 1`` exactly,
    so a least-squares fit of order ``points - 1`` or less on them is well conditioned."""
    if not (isinstance(points, int) and points >= 1):
        raise ValueError(f"points must be a positive integer (nodes per design axis), got {points!r}")
    nodes = torch.from_numpy(np.polynomial.legendre.leggauss(points)[0])
    inputs = UniformInputs([length_range[0], density_range[0]], [length_range[1], density_range[1]])
    grid = torch.stack(torch.meshgrid(nodes, nodes, indexing="ij"), -1).reshape(-1, 2)
    return inputs.from_unit(grid)


def uniform_designs(n: int, length_range: Sequence[float], density_range: Sequence[float],
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """``[n, 2]`` designs drawn uniformly from the box (the SE design distribution)."""
    return _uniform(UniformInputs([length_range[0], density_range[0]], [length_range[1], density_range[1]]), n,
                    generator)


def _uniform(inputs: UniformInputs, n: int, generator: torch.Generator | None) -> torch.Tensor:
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"n must be a positive integer, got {n!r}")
    return inputs.from_unit(torch.rand(n, inputs.dimension, generator=generator, dtype=torch.float64) * 2 - 1)


@dataclass
class DesignResponse:
    """Every coordinate at every step as a PCE in (l, rho): ``[steps, features]`` expansions on one basis.

    The expansion's outputs are the steps x features flattened, so one least-squares solve
    fits them all.
    """

    expansion: PolynomialChaos
    steps: int
    features: int

    @classmethod
    def fit(cls, designs: torch.Tensor, trajectories: torch.Tensor, length_range: Sequence[float],
            density_range: Sequence[float], order: int = 4) -> DesignResponse:
        """Least squares on episodes at ``designs [n, 2]`` with ``trajectories [n, steps, features]``.

        Raises a ValueError naming the problem: shapes that disagree, a design outside the box,
        non-finite observations, fewer episodes than terms (``C(order + 2, 2)``)."""
        designs, trajectories = torch.as_tensor(designs, dtype=torch.float64), torch.as_tensor(trajectories)
        if designs.dim() != 2 or designs.shape[1] != 2:
            raise ValueError(f"designs must be shaped [n, 2] (l, rho), got {tuple(designs.shape)}")
        if trajectories.dim() != 3 or trajectories.shape[0] != designs.shape[0]:
            raise ValueError(f"trajectories must be shaped [{designs.shape[0]}, steps, features] (one episode per "
                             f"design), got {tuple(trajectories.shape)}")
        low, high = [length_range[0], density_range[0]], [length_range[1], density_range[1]]
        _, steps, features = trajectories.shape
        expansion = PolynomialChaos.fit(designs, trajectories.double().flatten(1), low, high, order)
        return cls(expansion, steps, features)

    def __call__(self, designs: torch.Tensor) -> torch.Tensor:
        """``[n, steps, features]``: the episode the expansion predicts for each design (inside the box)."""
        return self.expansion(torch.as_tensor(designs, dtype=torch.float64)).unflatten(-1, (self.steps,
                                                                                           self.features))

    def mean(self) -> torch.Tensor:
        """``[steps, features]``: each coordinate's mean over the uniform design box, from the coefficients."""
        return self.expansion.mean().reshape(self.steps, self.features)

    def variance(self) -> torch.Tensor:
        """``[steps, features]``: each coordinate's variance over the design box, from the coefficients."""
        return self.expansion.variance().reshape(self.steps, self.features)

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``[n, steps, features]``: episodes at ``n`` uniform random designs, from the expansion (no physics)."""
        return self(_uniform(self.expansion.inputs, n, generator))
