"""Legendre polynomial chaos: uniform inputs, multi-index sets and the design matrix.

Every input is uniform on its own range ``[low, high]`` and mapped affinely to ``z`` in
[-1, 1], where the Legendre polynomials are orthogonal under the uniform density 1/2:
``E[P_m P_n] = delta_mn / (2n + 1)``. A multivariate term is a product of univariate ones,
``Psi_a(z) = prod_j P_{a_j}(z_j)``, so ``E[Psi_a^2] = prod_j 1 / (2 a_j + 1)`` (the thesis'
``diag(alpha!)`` is the Hermite norm, wrong for Legendre). The basis here is orthonormal by
default (``sqrt(2n + 1) P_n``): every norm is 1, the Gram matrix of a good sample is close to
the identity and the variance is the plain sum of squared coefficients.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch

TRUNCATIONS = ("total_degree", "hyperbolic")


def _check_order(order: int) -> None:
    if not (isinstance(order, int) and not isinstance(order, bool) and order >= 0):
        raise ValueError(f"order must be an integer >= 0, got {order!r}")


def multi_indices(dimension: int, order: int, truncation: str = "total_degree", q: float = 1.0,
                  max_interaction: int | None = None) -> torch.Tensor:
    """The multi-index set ``[terms, dimension]`` (long), ordered by total degree, the constant first.

    ``total_degree``: ``sum_j a_j <= order`` (``C(dimension + order, order)`` terms).
    ``hyperbolic``: the q-norm ``(sum_j a_j^q)^(1/q) <= order`` with ``0 < q <= 1`` (Blatman
    and Sudret 2011): ``q = 1`` is the total degree, smaller ``q`` keeps the high univariate
    degrees and drops high-order interactions (sparsity of effects).
    ``max_interaction``: at most this many inputs in one term (None: no limit).
    """
    if not (isinstance(dimension, int) and dimension >= 1):
        raise ValueError(f"dimension must be an integer >= 1, got {dimension!r}")
    _check_order(order)
    if truncation not in TRUNCATIONS:
        raise ValueError(f"truncation must be one of {TRUNCATIONS}, got {truncation!r}")
    if not 0 < q <= 1:  # checked whatever the truncation, so a bad setting never waits for a switch to hyperbolic
        raise ValueError(f"q must lie in (0, 1] (the hyperbolic truncation's q-norm), got {q!r}")
    if max_interaction is not None and not (isinstance(max_interaction, int) and max_interaction >= 1):
        raise ValueError(f"max_interaction must be an integer >= 1 or None, got {max_interaction!r}")
    rank = min(dimension, order if max_interaction is None else min(max_interaction, order))
    limit = order**q + 1e-9 if truncation == "hyperbolic" else order
    rows = [(0,) * dimension]
    for degree in range(1, order + 1):
        found = []
        # A term of total degree `degree` touches k <= min(rank, degree) inputs, each with degree >= 1.
        for k in range(1, min(rank, degree) + 1):
            for parts in _compositions(degree, k):
                if truncation == "hyperbolic" and sum(a**q for a in parts) > limit:
                    continue
                for dims in itertools.combinations(range(dimension), k):
                    row = [0] * dimension
                    for d, a in zip(dims, parts, strict=True):
                        row[d] = a
                    found.append(tuple(row))
        rows += sorted(found, reverse=True)
    return torch.tensor(rows, dtype=torch.long, device="cpu")  # index bookkeeping: always on the CPU


def _compositions(total: int, parts: int) -> list[tuple[int, ...]]:
    """Ordered ways of writing ``total`` as ``parts`` positive integers."""
    return [tuple(b - a for a, b in zip((0, *cut), (*cut, total), strict=True))
            for cut in itertools.combinations(range(1, total), parts - 1)]


def total_degree_terms(dimension: int, order: int) -> int:
    """``C(dimension + order, order)``: the size of the total-degree basis."""
    return math.comb(dimension + order, order)


def squared_norms(indices: torch.Tensor, orthonormal: bool = True) -> torch.Tensor:
    """``E[Psi_a^2]`` under the uniform measure on [-1, 1]^d: 1 when orthonormal, else ``prod 1/(2 a_j + 1)``."""
    if orthonormal:
        return torch.ones(indices.shape[0], dtype=torch.float64, device="cpu")
    return (1.0 / (2.0 * indices.double() + 1.0)).prod(-1)


def legendre(z: torch.Tensor, order: int, orthonormal: bool = True) -> torch.Tensor:
    """``[..., order + 1]``: ``P_0(z) .. P_order(z)`` by the three-term recurrence
    ``(n + 1) P_{n+1} = (2n + 1) z P_n - n P_{n-1}``; scaled by ``sqrt(2n + 1)`` when orthonormal."""
    _check_order(order)
    values = [torch.ones_like(z)]
    if order >= 1:
        values.append(z)
    for n in range(1, order):
        values.append(((2 * n + 1) * z * values[n] - n * values[n - 1]) / (n + 1))
    out = torch.stack(values, dim=-1)
    if orthonormal:
        out = out * torch.sqrt(2.0 * torch.arange(order + 1, dtype=z.dtype, device=z.device) + 1.0)
    return out


class Basis:
    """A multi-index set and how to evaluate it: ``basis(z) -> [..., terms]`` for ``z`` in [-1, 1]^d.

    Each term is stored as its (at most ``rank``) non-zero factors, so building the design
    matrix costs ``rank`` gathers and products per term, not ``d``: 3 for an order-3 basis
    however many inputs it has.
    """

    def __init__(self, indices: torch.Tensor, orthonormal: bool = True) -> None:
        self.indices = indices.long().cpu()
        self.orthonormal = orthonormal
        self.dimension = int(indices.shape[1])
        self.order = int(indices.max()) if indices.numel() else 0
        rank = max(1, int((indices > 0).sum(1).max()))
        # Column j * (order + 1) + a of the flattened univariate table is P_a(z_j); the last column is 1.
        ones = self.dimension * (self.order + 1)
        factors = torch.full((indices.shape[0], rank), ones, dtype=torch.long, device="cpu")
        for term, row in enumerate(indices.tolist()):
            active = [(j, a) for j, a in enumerate(row) if a > 0]
            for k, (j, a) in enumerate(active):
                factors[term, k] = j * (self.order + 1) + a
        self.factors = factors

    @classmethod
    def create(cls, dimension: int, order: int, truncation: str = "total_degree", q: float = 1.0,
               max_interaction: int | None = None, orthonormal: bool = True) -> Basis:
        return cls(multi_indices(dimension, order, truncation, q, max_interaction), orthonormal)

    @property
    def terms(self) -> int:
        return int(self.indices.shape[0])

    def squared_norms(self) -> torch.Tensor:
        return squared_norms(self.indices, self.orthonormal)

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        """``[..., samples, terms]``: the design matrix at ``z`` ``[..., samples, dimension]`` (a
        transposed view of :meth:`transposed`, which matrix products take as it is)."""
        return self.transposed(z).transpose(-1, -2)

    def transposed(self, z: torch.Tensor) -> torch.Tensor:
        """``[..., terms, samples]``: the design matrix transposed, built one term per row.

        Terms first because each factor is then a gather of whole rows of the univariate
        table (contiguous copies along the samples); gathering columns of a samples-first
        table is strided, and building the matrix would then cost more than its Gram product."""
        if z.shape[-1] != self.dimension:
            raise ValueError(f"the basis has {self.dimension} inputs, got {z.shape[-1]}")
        table = legendre(z, self.order, self.orthonormal).flatten(-2)
        table = torch.cat([table, torch.ones_like(table[..., :1])], dim=-1).transpose(-1, -2).contiguous()
        factors = self.factors.to(z.device)
        out = table.index_select(-2, factors[:, 0])
        for k in range(1, factors.shape[1]):
            out.mul_(table.index_select(-2, factors[:, k]))
        return out


class UniformInputs:
    """Inputs uniform on ``[low, high]`` (per input), mapped affinely to [-1, 1].

    :meth:`to_unit` refuses a value outside its range (a ValueError naming it), or clamps it
    when asked (a surrogate queried a little outside its training data).
    """

    def __init__(self, low: Sequence[float] | torch.Tensor, high: Sequence[float] | torch.Tensor) -> None:
        low = torch.as_tensor(low, dtype=torch.float64).reshape(-1)
        high = torch.as_tensor(high, dtype=torch.float64).reshape(-1)
        if low.shape != high.shape:
            raise ValueError(f"low and high must have the same length, got {low.numel()} and {high.numel()}")
        bad = ~(torch.isfinite(low) & torch.isfinite(high) & (high > low))
        if bad.any():
            i = int(bad.nonzero()[0])
            raise ValueError(f"input {i}: the range must be finite with low < high, got [{float(low[i])!r}, "
                             f"{float(high[i])!r}]")
        self.low, self.high = low, high

    @property
    def dimension(self) -> int:
        return int(self.low.numel())

    def to_unit(self, x: torch.Tensor, clamp: bool = False) -> torch.Tensor:
        if x.shape[-1] != self.dimension:
            raise ValueError(f"expected {self.dimension} inputs, got {x.shape[-1]}")
        low, high = self.low.to(x.device, x.dtype), self.high.to(x.device, x.dtype)
        z = (2.0 * x - (low + high)) / (high - low)
        if clamp:
            return z.clamp(-1.0, 1.0)
        outside = ~((z >= -1.0 - 1e-6) & (z <= 1.0 + 1e-6))  # also catches NaN
        if outside.any():
            row, i = (int(v) for v in outside.reshape(-1, self.dimension).nonzero()[0])
            value = float(x.reshape(-1, self.dimension)[row, i])
            raise ValueError(f"input {i} = {value:.6g} lies outside its uniform range "
                             f"[{float(self.low[i]):.6g}, {float(self.high[i]):.6g}]")
        return z.clamp(-1.0, 1.0)

    def from_unit(self, z: torch.Tensor) -> torch.Tensor:
        low, high = self.low.to(z.device, z.dtype), self.high.to(z.device, z.dtype)
        return 0.5 * (low + high) + 0.5 * (high - low) * z
