"""A fitted polynomial chaos expansion: evaluation, moments, Sobol' indices and the thesis' reduction step."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from unipolicy_rl.polynomial_chaos.basis import Basis, UniformInputs
from unipolicy_rl.polynomial_chaos.regression import FitDiagnostics, least_squares
from unipolicy_rl.polynomial_chaos.sensitivity import SobolIndices, sobol_indices
from unipolicy_rl.polynomial_chaos.sparse import SparseFit, sparse_least_squares

REDUCTIONS = ("projection", "variance")


def constant_inputs(x: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """``[..., d]`` (bool): which inputs take one value over every sample of a problem, for samples
    ``x [..., n, d]`` and ``weights [..., n]`` (a sample of weight 0 is not part of the fit)."""
    used = torch.ones_like(x[..., :1], dtype=torch.bool) if weights is None else (weights > 0).unsqueeze(-1)
    low = torch.where(used, x, torch.full_like(x, float("inf"))).amin(-2)
    high = torch.where(used, x, torch.full_like(x, float("-inf"))).amax(-2)
    return low == high


def mean(coefficients: torch.Tensor) -> torch.Tensor:
    """``E[y] = c_0``: the constant term (``Psi_0 = 1``), ``[..., outputs]`` from ``[..., terms, outputs]``."""
    return coefficients[..., 0, :]


def variance(coefficients: torch.Tensor, norms: torch.Tensor) -> torch.Tensor:
    """``V[y] = sum_{a != 0} c_a^2 E[Psi_a^2]``, ``[..., outputs]`` (``norms``: ``[terms]``, the constant first)."""
    return (coefficients[..., 1:, :].pow(2) * norms[1:].to(coefficients).unsqueeze(-1)).sum(-2)


class PolynomialChaos:
    """``y(x) = sum_a c_a Psi_a(z(x))`` for inputs uniform on ``[low, high]``.

    ``coefficients`` are ``[..., terms, outputs]``: leading dims index independent
    expansions on the same basis (time steps, elements, members).

    >>> pce = PolynomialChaos.fit(x, y, low, high, order=3)    # doctest: +SKIP
    >>> pce.mean(), pce.variance()                              # doctest: +SKIP
    """

    def __init__(self, inputs: UniformInputs, basis: Basis, coefficients: torch.Tensor,
                 diagnostics: FitDiagnostics | None = None) -> None:
        if basis.dimension != inputs.dimension:
            raise ValueError(f"the basis has {basis.dimension} inputs, the ranges {inputs.dimension}")
        if coefficients.shape[-2] != basis.terms:
            raise ValueError(f"coefficients have {coefficients.shape[-2]} terms, the basis {basis.terms}")
        self.inputs, self.basis, self.coefficients, self.diagnostics = inputs, basis, coefficients, diagnostics

    @classmethod
    def fit(cls, x: torch.Tensor, y: torch.Tensor, low: Sequence[float] | torch.Tensor,
            high: Sequence[float] | torch.Tensor, order: int, truncation: str = "total_degree", q: float = 1.0,
            max_interaction: int | None = None, orthonormal: bool = True, weights: torch.Tensor | None = None,
            ridge: float = 0.0) -> PolynomialChaos:
        """Least squares on samples ``x [..., n, d]`` (inside the ranges) and ``y [..., n, outputs]``.

        An input that never varies over a problem's samples (non-zero weights) says nothing about
        how the output depends on it, and its terms' columns are multiples of lower terms' (the
        basis is downward closed, as every truncation here builds it), which makes the normal
        equations singular. Its terms are dropped there: their coefficients are zero, so the
        moments attribute nothing to it, the fit of the rest reaches the least-squares optimum,
        and ``diagnostics.constant_inputs`` names the input."""
        inputs = UniformInputs(low, high)
        basis = Basis.create(inputs.dimension, order, truncation, q, max_interaction, orthonormal)
        n = x.shape[-2]
        if n < basis.terms:  # refused before the design matrix is built
            raise ValueError(f"underdetermined fit: {basis.terms} terms but only {n} samples")
        design = basis(inputs.to_unit(x))
        constant = constant_inputs(x, weights)
        involves = (basis.indices > 0).to(constant.device)
        dropped = (constant.unsqueeze(-2) & involves).any(-1)  # [..., terms]: a term of a constant input
        coefficients, diagnostics = least_squares(design, y.to(design.dtype), weights, ridge,
                                                  dropped=dropped if dropped.any() else None)
        diagnostics.constant_inputs = tuple(int(j) for j in constant.reshape(-1, inputs.dimension).any(0).nonzero())
        return cls(inputs, basis, coefficients, diagnostics)

    @classmethod
    def fit_sparse(cls, x: torch.Tensor, y: torch.Tensor, low: Sequence[float] | torch.Tensor,
                   high: Sequence[float] | torch.Tensor, order: int, truncation: str = "hyperbolic", q: float = 0.5,
                   max_interaction: int | None = 2, weights: torch.Tensor | None = None, max_terms: int | None = None,
                   patience: int = 10, tolerance: float = 0.0) -> tuple[PolynomialChaos, SparseFit]:
        """Adaptive sparse fit (:func:`~unipolicy_rl.polynomial_chaos.sparse.sparse_least_squares`):
        each output keeps the terms of the candidate basis (``order``, ``truncation``, ``q``,
        ``max_interaction``) that its corrected leave-one-out error chooses; the others are zero,
        so the moments and sensitivities read from the coefficients as for any expansion.

        Terms of an input that never varies over a problem's samples are no candidates (their
        columns repeat lower terms'). Unlike :meth:`fit`, fewer samples than candidate terms is
        no error: the path stops one term short of the samples. Returns the expansion and the
        selection's record (terms, leave-one-out errors along the path)."""
        inputs = UniformInputs(low, high)
        basis = Basis.create(inputs.dimension, order, truncation, q, max_interaction)
        design = basis(inputs.to_unit(x))
        constant = constant_inputs(x, weights)
        involves = (basis.indices > 0).to(constant.device)
        candidates = ~(constant.unsqueeze(-2) & involves).any(-1)  # [..., terms]
        fit = sparse_least_squares(design, y.to(design.dtype), weights, candidates, max_terms, patience,
                                   tolerance)
        return cls(inputs, basis, fit.coefficients.to(design.dtype)), fit

    def __call__(self, x: torch.Tensor, clamp: bool = False) -> torch.Tensor:
        """``[..., n, outputs]`` at ``x [..., n, d]`` (leading dims broadcast against the coefficients')."""
        design = self.basis(self.inputs.to_unit(x, clamp=clamp)).to(self.coefficients.dtype)
        return design @ self.coefficients

    def norms(self) -> torch.Tensor:
        return self.basis.squared_norms()

    def mean(self) -> torch.Tensor:
        return mean(self.coefficients)

    def variance(self) -> torch.Tensor:
        return variance(self.coefficients, self.norms())

    def sobol_indices(self) -> SobolIndices:
        """First-order and total Sobol' indices ``[..., outputs, inputs]`` from the coefficients
        (:func:`~unipolicy_rl.polynomial_chaos.sobol_indices`)."""
        return sobol_indices(self.basis.indices, self.coefficients, self.norms())

    def reduce(self, drop: Sequence[int], mode: str = "projection") -> PolynomialChaos:
        """The expansion without the inputs ``drop`` (see :func:`reduce`)."""
        indices, coefficients = reduce(self.coefficients, self.basis.indices, drop, mode, self.norms())
        keep = [j for j in range(self.inputs.dimension) if j not in set(drop)]
        inputs = UniformInputs(self.inputs.low[keep], self.inputs.high[keep])
        return PolynomialChaos(inputs, Basis(indices[:, keep], self.basis.orthonormal), coefficients)


def reduce(coefficients: torch.Tensor, indices: torch.Tensor, drop: Sequence[int], mode: str = "projection",
           norms: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The thesis' reduction step (section 4.1.1): remove inputs (the oldest action of the window)
    from an expansion, keeping its mean, and its variance where the mode says so.

    ``projection``: the L2 projection on the terms without the dropped inputs, which is the
    conditional expectation ``E[y | kept inputs]`` (the inputs are independent): the mean is
    kept (``c_0``), the variance drops by exactly the dropped inputs' share (their total
    Sobol part, ``sum`` of ``c_a^2 E[Psi_a^2]`` over terms that involve them).

    ``variance``: the thesis' choice (eq. 4.9: reduced coefficients whose variance equals the
    full one), solved in closed form along the projection: every kept non-constant coefficient
    scaled by ``sqrt(V_full / V_projected)`` per output, with the Legendre norms
    ``E[Psi_a^2] = prod 1/(2 a_j + 1)`` (not the Hermite ``a!`` of the thesis' eq. 4.8). An output
    whose kept terms carry no variance keeps the projection.

    Returns the kept multi-indices (full width; the dropped columns are zero) and their
    coefficients ``[..., kept terms, outputs]``.
    """
    if mode not in REDUCTIONS:
        raise ValueError(f"reduction must be one of {REDUCTIONS}, got {mode!r}")
    drop = list(drop)
    bad = [j for j in drop if not 0 <= j < indices.shape[1]]
    if bad:
        raise ValueError(f"cannot drop input {bad[0]}: the expansion has {indices.shape[1]} inputs")
    norms = torch.ones(indices.shape[0], dtype=torch.float64) if norms is None else norms
    kept = (indices[:, drop] == 0).all(-1) if drop else torch.ones(indices.shape[0], dtype=torch.bool)
    reduced = coefficients[..., kept, :]
    if mode == "variance":
        full = variance(coefficients, norms)
        projected = variance(reduced, norms[kept])
        scale = torch.where(projected > 0, (full / projected.clamp_min(torch.finfo(full.dtype).tiny)).sqrt(),
                            torch.ones_like(full))
        reduced = torch.cat([reduced[..., :1, :], reduced[..., 1:, :] * scale.unsqueeze(-2)], dim=-2)
    return indices[kept], reduced
