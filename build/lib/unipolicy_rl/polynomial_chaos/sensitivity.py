"""Sobol' indices from a polynomial chaos expansion's coefficients (Sudret 2008), no sampling.

For independent inputs and a basis orthogonal under their law, the expansion is the function's
ANOVA decomposition grouped by term: the variance is ``V = sum_{a != 0} c_a^2 E[Psi_a^2]``, and
the part of it carried by the terms in input ``i`` alone is input ``i``'s first-order share, the
part carried by every term that involves ``i`` its total share:

    S_i  = sum_{a: a_i > 0, a_j = 0 for j != i} c_a^2 E[Psi_a^2] / V
    ST_i = sum_{a: a_i > 0} c_a^2 E[Psi_a^2] / V

so ``0 <= S_i <= ST_i <= 1``, the first-order indices sum to at most 1 (the rest is
interactions) and the total indices to at least 1. The squared norms ``E[Psi_a^2]`` are 1 for
the orthonormal basis this library builds by default and ``prod_j 1/(2 a_j + 1)`` for plain
Legendre polynomials (:func:`~unipolicy_rl.polynomial_chaos.squared_norms`); leaving them out
for a non-orthonormal basis would overweight every higher-degree term.

The indices are those of the *expansion* under its input measure (independent uniform inputs on
their ranges), which is the point of reading them from coefficients: exact for the fitted
function, free once it is fitted. For a model fitted to correlated data (a robot's states) they
describe the fitted function on the box of its inputs, not the data's own variance split.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from unipolicy_rl.polynomial_chaos.basis import squared_norms


@dataclass(frozen=True)
class SobolIndices:
    """``first`` and ``total`` ``[..., outputs, inputs]``, ``variance`` ``[..., outputs]``.

    An output the expansion holds constant (no variance) has indices 0: no input moves it."""

    first: torch.Tensor
    total: torch.Tensor
    variance: torch.Tensor

    @property
    def interaction(self) -> torch.Tensor:
        """``[..., outputs]``: the share of each output's variance carried by terms of two or more inputs."""
        return torch.where(self.variance > 0, 1.0 - self.first.sum(-1), torch.zeros_like(self.variance))


def sobol_indices(indices: torch.Tensor, coefficients: torch.Tensor, norms: torch.Tensor | None = None) -> SobolIndices:
    """First-order and total Sobol' indices of every output of an expansion.

    Args:
        indices: the multi-index set ``[terms, inputs]`` (the constant term is the all-zero row,
            wherever it sits).
        coefficients: ``[..., terms, outputs]``; leading dims are independent expansions on the
            same basis (members, time steps).
        norms: ``E[Psi_a^2]`` per term ``[terms]``; None for an orthonormal basis (all 1).

    Raises:
        ValueError: the coefficients' terms do not match the multi-index set's, or a norm is
            not positive, naming the sizes or the term.
    """
    terms = indices.shape[0]
    if coefficients.shape[-2] != terms:
        raise ValueError(f"coefficients have {coefficients.shape[-2]} terms, the multi-index set {terms}")
    dtype = torch.float64
    norms = squared_norms(indices) if norms is None else norms
    norms = norms.to(coefficients.device, dtype)
    if norms.shape != (terms,) or not (norms > 0).all():
        raise ValueError(f"norms must be {terms} positive numbers (E[Psi_a^2] per term), got shape "
                         f"{tuple(norms.shape)} with minimum {float(norms.min()) if norms.numel() else 'none'}")
    active = (indices > 0).to(coefficients.device)
    order = active.sum(-1)
    part = coefficients.to(dtype).pow(2) * (norms * (order > 0)).unsqueeze(-1)  # the constant carries no variance
    variance = part.sum(-2)
    alone = (active & (order == 1).unsqueeze(-1)).to(dtype)
    # [..., terms, outputs] x [terms, inputs] -> [..., outputs, inputs]
    first = part.transpose(-1, -2) @ alone
    total = part.transpose(-1, -2) @ active.to(dtype)
    scale = torch.where(variance > 0, 1.0 / variance.clamp_min(torch.finfo(dtype).tiny), torch.zeros_like(variance))
    return SobolIndices(first * scale.unsqueeze(-1), total * scale.unsqueeze(-1), variance)


__all__ = ["SobolIndices", "sobol_indices"]
