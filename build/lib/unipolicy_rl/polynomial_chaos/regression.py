"""Polynomial-chaos coefficients by least squares, many problems in one batched solve.

Every problem (an output, a time step, an element, a bootstrap member) shares the basis;
batching them turns thousands of small fits into a few large matrix products. The solver
forms the normal equations ``(X^T W X) c = X^T W Y`` and solves them by Cholesky: cheap, and
well conditioned for an orthonormal basis on a good sample (its Gram matrix is close to
``n I``). A problem Cholesky cannot factor falls back to a rank-revealing least-squares solve
on its own rows (:func:`rank_revealing_lstsq`), which reaches the least-squares optimum however
singular the problem; a fit that is still not finite raises with its diagnostics rather than
return NaN.

Terms the caller knows carry no information (those of an input that never varies, whose columns
repeat lower terms') can be dropped: their coefficients are held at exactly zero, and the rest
solve as if those columns were not there.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class FitDiagnostics:
    """How a batch of least-squares fits went, one entry per problem.

    ``condition``: an estimate of the design matrix's condition number, the ratio of the
    largest to the smallest diagonal entry of the Cholesky factor of ``X^T W X`` (a lower bound
    of cond(X); 1 for a perfectly orthogonal sample); ``exact_condition`` asks for the exact
    one (an eigendecomposition per problem). ``residual_rms``: root-mean-square training
    residual per problem and output. ``fallbacks``: problems solved by
    :func:`rank_revealing_lstsq` instead (``failed`` flags them). ``dropped``: ``[..., terms]``,
    the terms held at zero per problem (None: none were). ``constant_inputs``: the inputs that
    never varied over the samples of some problem, whose terms were dropped there (filled in by
    :meth:`~unipolicy_rl.polynomial_chaos.PolynomialChaos.fit`, which knows the inputs).
    """

    samples: torch.Tensor
    terms: int
    condition: torch.Tensor
    residual_rms: torch.Tensor
    fallbacks: int
    failed: torch.Tensor
    dropped: torch.Tensor | None = None
    constant_inputs: tuple[int, ...] = ()

    def summary(self) -> dict[str, float]:
        return {
            "terms": float(self.terms),
            "min_samples": float(self.samples.min()),
            "max_condition": float(self.condition.max()),
            "mean_residual_rms": float(self.residual_rms.mean()),
            "fallbacks": float(self.fallbacks),
            "dropped_terms": float(self.dropped.sum()) if self.dropped is not None else 0.0,
            "constant_inputs": float(len(self.constant_inputs)),
        }


def rank_revealing_lstsq(matrix: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The minimum-norm least-squares solution of ``matrix @ c = targets`` (batched), correct when
    ``matrix`` is rank deficient: the fallback of every solve in this package, which runs where
    the normal equations are singular or nearly so.

    The driver is LAPACK's SVD-based ``gelsd``. ``torch.linalg.lstsq``'s CPU default, ``gelsy``
    (QR with column pivoting), can misjudge the rank of such a matrix and return coefficients
    that do not even fit their training data, silently (pytorch/pytorch#71222; a constant input
    of a PCE triggers it); on CUDA its only driver, ``gels``, assumes full rank. So a problem on
    another device is solved on the CPU and its solution moved back: fallbacks are few and
    small, and the copy costs less than a wrong fit.
    """
    solution = torch.linalg.lstsq(matrix.cpu(), targets.cpu(), driver="gelsd").solution
    return solution.to(matrix.device)


def least_squares(design: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor | None = None,
                  ridge: float = 0.0, exact_condition: bool = False,
                  dropped: torch.Tensor | None = None) -> tuple[torch.Tensor, FitDiagnostics]:
    """Coefficients ``[..., terms, outputs]`` minimising ``sum_i w_i |y_i - x_i c|^2`` per problem.

    Args:
        design: ``[..., n, terms]``, the basis evaluated at the samples (problems in the leading dims).
        targets: ``[..., n, outputs]``.
        weights: ``[..., n]`` sample weights (0 leaves a row out: padding, another element's
            sample, a bootstrap draw), or None for all ones.
        ridge: Tikhonov term added to the normal equations' diagonal (0: plain least squares).
        exact_condition: compute cond(X) exactly (an eigendecomposition per problem).
        dropped: ``[..., terms]`` (bool), terms to hold at zero per problem, or None for none.
            Their columns leave the design and the rest are fitted without them; their
            coefficients are exactly zero and the condition figures are those of the kept terms.

    Raises:
        ValueError: non-finite inputs, or a problem with fewer samples (non-zero weights) than
            terms (an underdetermined fit), before anything is solved.
    """
    if design.shape[:-1] != targets.shape[:-1]:
        raise ValueError(f"design {tuple(design.shape)} and targets {tuple(targets.shape)} disagree on the samples")
    if not ridge >= 0:
        raise ValueError(f"ridge must be >= 0, got {ridge!r}")
    for name, tensor in (("design", design), ("targets", targets)):
        if not torch.isfinite(tensor).all():
            raise ValueError(f"{name} has non-finite values")
    terms = design.shape[-1]
    if weights is None:
        weights = torch.ones(design.shape[:-1], dtype=design.dtype, device=design.device)
    samples = (weights > 0).sum(-1)
    if (samples < terms).any():
        raise ValueError(f"underdetermined fit: {terms} terms but only {int(samples.min())} samples in a problem; "
                         f"use more samples or a smaller basis (lower order, hyperbolic truncation)")
    if dropped is not None:
        if dropped.all(-1).any():
            raise ValueError("dropped holds every term of a problem at zero: keep at least one (the constant)")
        dropped = dropped.to(torch.bool).expand(design.shape[:-2] + design.shape[-1:])
        design = design.masked_fill(dropped.unsqueeze(-2), 0.0)
    weighted = design * weights.unsqueeze(-1)
    gram = weighted.transpose(-1, -2) @ design
    moment = weighted.transpose(-1, -2) @ targets
    if dropped is not None:
        _pin(gram, dropped)
    target_square = (targets.pow(2) * weights.unsqueeze(-1)).sum(-2)
    coefficients, diagnostics = solve_normal_equations(gram, moment, target_square, samples, ridge, exact_condition)
    if diagnostics.fallbacks:
        failed = diagnostics.failed
        root = weights.clamp_min(0).sqrt().unsqueeze(-1)
        rows = (design * root)[failed]
        coefficients[failed] = rank_revealing_lstsq(rows, (targets * root)[failed])
        kept = torch.full(failed.shape, terms, device=design.device) if dropped is None else (~dropped).sum(-1)
        diagnostics.condition[failed] = _condition(rows, kept[failed])
    if dropped is not None:
        coefficients = coefficients.masked_fill(dropped.unsqueeze(-1), 0.0)
        diagnostics.dropped = dropped
    # With the rows at hand the residual is computed directly (the normal-equation form cancels digits).
    residual = (design @ coefficients - targets) * weights.clamp_min(0).sqrt().unsqueeze(-1)
    diagnostics.residual_rms = (residual.pow(2).sum(-2) / samples.unsqueeze(-1).to(residual.dtype)).sqrt()
    if not torch.isfinite(coefficients).all():
        raise FloatingPointError(f"least squares gave non-finite coefficients: {diagnostics.summary()}")
    return coefficients, diagnostics


def solve_normal_equations(gram: torch.Tensor, moment: torch.Tensor, target_square: torch.Tensor,
                           samples: torch.Tensor, ridge: float = 0.0, exact_condition: bool = False,
                           factor_dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, FitDiagnostics]:
    """Solves ``(G + ridge I) c = X^T W Y`` by Cholesky, for Gram matrices accumulated by the caller
    (over row chunks, so the design matrix of a large sample is never held at once).

    ``gram`` ``[..., terms, terms]``, ``moment`` ``[..., terms, outputs]``, ``target_square``
    ``[..., outputs]`` (``sum w y^2``, for the residual), ``samples`` ``[...]`` (rows with
    non-zero weight). Problems Cholesky cannot factor are flagged in ``diagnostics.failed``
    (coefficients there are zero) for the caller to solve another way.

    The Cholesky runs in ``factor_dtype``: float64 by default (cheap next to forming the Gram
    matrix). A caller whose Gram matrices were accumulated in float32 gains nothing from a
    float64 factor (the sums carry float32's error already) and may pass float32, which halves
    the memory traffic of a large batch; problems float32 cannot factor are then factored
    again in float64 before any is reported as failed.
    """
    terms = gram.shape[-1]
    if (samples < terms).any():
        raise ValueError(f"underdetermined fit: {terms} terms but only {int(samples.min())} samples in a problem; "
                         f"use more samples or a smaller basis (lower order, hyperbolic truncation)")
    dtype = moment.dtype
    given = gram
    gram = _with_ridge(given, ridge, factor_dtype)
    coefficients, condition, failed = _cholesky_solve(gram, moment.to(factor_dtype))
    if factor_dtype != torch.float64 and failed.any():
        gram, moment = _with_ridge(given, ridge, torch.float64), moment.double()
        coefficients, condition = coefficients.double(), condition.double()
        coefficients[failed], condition[failed], failed[failed] = _cholesky_solve(gram[failed], moment[failed])
    moment = moment.to(gram.dtype)
    coefficients = torch.where(failed.reshape(*failed.shape, 1, 1), torch.zeros_like(coefficients), coefficients)
    if exact_condition:
        eigenvalues = torch.linalg.eigvalsh(gram).clamp_min(0)
        condition = (eigenvalues[..., -1] / eigenvalues[..., 0].clamp_min(torch.finfo(gram.dtype).tiny)).sqrt()
    # Residual sum of squares from the normal equations: y'Wy - 2 c'X'Wy + c'Gc (no second pass over the rows),
    # summed in float64 whatever the factor's precision, since the three terms nearly cancel.
    rss = (target_square.double() - 2 * (coefficients * moment).double().sum(-2)
           + (coefficients * (gram @ coefficients)).double().sum(-2))
    residual_rms = (rss.clamp_min(0) / samples.unsqueeze(-1).to(rss.dtype)).sqrt()
    condition = torch.where(failed, torch.full_like(condition, float("inf")), condition)
    diagnostics = FitDiagnostics(samples, terms, condition.to(dtype), residual_rms.to(dtype), int(failed.sum()), failed)
    return coefficients.to(dtype), diagnostics


def _pin(gram: torch.Tensor, dropped: torch.Tensor) -> None:
    """Gives the dropped terms' (zero) rows of ``gram`` a diagonal, in place, so each solves to zero.

    The diagonal is that of the problem's first kept term: it lies within the kept block's
    eigenvalues (a diagonal entry is a Rayleigh quotient), and the Cholesky factor's entry there
    equals the first kept term's, so neither condition figure changes."""
    first = (~dropped).to(torch.int8).argmax(-1, keepdim=True)
    diagonal = gram.diagonal(dim1=-2, dim2=-1)
    diagonal.copy_(torch.where(dropped, diagonal.gather(-1, first), diagonal))


def _condition(matrix: torch.Tensor, kept: torch.Tensor) -> torch.Tensor:
    """cond(matrix) over its ``kept`` non-zero columns: the largest singular value over the
    ``kept``-th (the dropped columns are zero, so they only add trailing zero singular values)."""
    singular = torch.linalg.svdvals(matrix)
    return singular[..., 0] / singular.gather(-1, (kept - 1).unsqueeze(-1)).squeeze(-1)


def _with_ridge(gram: torch.Tensor, ridge: float, dtype: torch.dtype) -> torch.Tensor:
    """``gram + ridge I`` in ``dtype``, never writing into the caller's tensor."""
    if not ridge:
        return gram.to(dtype)
    gram = gram.to(dtype, copy=True)
    gram.diagonal(dim1=-2, dim2=-1).add_(ridge)
    return gram


def _cholesky_solve(gram: torch.Tensor, moment: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coefficients, condition estimate and failure flag per problem, by Cholesky in the Gram's dtype."""
    factor, info = torch.linalg.cholesky_ex(gram)
    # Two triangular solves: what cholesky_solve does, through LAPACK's batched triangular solve, which is faster.
    coefficients = torch.linalg.solve_triangular(
        factor.mT, torch.linalg.solve_triangular(factor, moment, upper=False), upper=True)
    diagonal = torch.diagonal(factor, dim1=-2, dim2=-1).abs()
    condition = diagonal.amax(-1) / diagonal.amin(-1).clamp_min(torch.finfo(diagonal.dtype).tiny)
    failed = (info != 0) | ~torch.isfinite(coefficients).flatten(-2).all(-1)
    return coefficients, condition, failed
