"""Adaptive sparse least squares: per output, the terms and how many, chosen by leave-one-out error.

A full basis of order 4-5 in a hundred inputs has more terms than a policy's data can
determine, and most of them describe nothing the outputs depend on. Blatman and Sudret (2011)
select terms greedily and stop where the corrected leave-one-out error is lowest; this module
does that, batched over problems (outputs, bootstrap members) in torch.

The greedy step is orthogonal matching pursuit: at each step the candidate whose (normalised)
column correlates most with the current residual joins, and the coefficients are the
least-squares fit on the selected terms (Blatman and Sudret's hybrid LARS refits the same way;
only the order of selection differs). Dividing the correlation by what is left of the column
outside the selected span instead (the exact drop of the residual, "orthogonal least squares")
was tried on a walking policy's data and is worse: it favours columns nearly spanned by the
selected ones, which fit a few extreme rows with large coefficients: its leave-one-out error
passes 1 (no better than the mean) by 200 terms for most outputs, where this rule's is still
near its lowest (docs/results.md, "Polynomial chaos"). A column with (almost) nothing left
outside the selected span is never chosen.

Everything but the leave-one-out error runs on the normal equations (the Gram matrix
``X^T W X``, the moments ``X^T W Y``), one incremental Cholesky step per selected term, so the
cost does not grow with the number of samples once the Gram matrix is formed. The
leave-one-out residual of a row, ``e_i = r_i / (1 - h_ii)`` (``h_ii`` the leverage), needs the
row itself; it is tracked on the rows the caller hands over (all of them for a small fit, an
unbiased random subsample for a large one: the mean of ``e_i^2`` over a random subset estimates
the mean over all rows). It is multiplied by Chapelle's correction
``T = N / (N - k) * (1 + tr((X_A^T W X_A)^-1))`` (Blatman and Sudret 2011: the plain
estimate is optimistic when ``k`` terms are fitted to ``N`` samples) and divided by the output's
variance over those rows, so 1 means "no better than the mean".

A row of weight 0 (a bootstrap member that did not draw it) is not in the fit: its ``h_ii`` is
0 and its error is an honest out-of-bag error; a row drawn several times is left out with all its
copies (``h_ii = w_i x_i^T G^-1 x_i``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# A candidate whose column keeps less than this share of its squared norm outside the span of
# the selected terms is numerically dependent on them and is not selected.
DEPENDENCE_TOLERANCE = 1e-9
# Bytes of working memory per chunk of problems solved together.
CHUNK_BYTES = 256 * 2**20


@dataclass
class SparseFit:
    """The result of :func:`select_terms`, per problem (the leading dims) and output.

    ``coefficients`` ``[..., terms, outputs]``: the least-squares fit on each output's selected
    terms, exactly zero elsewhere. ``selected`` ``[..., terms, outputs]`` (bool).
    ``loo_error``: ``[..., outputs]``, the corrected relative leave-one-out error at the chosen
    sparsity. ``loo_path``: ``[..., outputs, steps]``, the same after each step of the greedy
    path (inf where the path ended). ``path``: ``[..., outputs, steps]``, the term each step
    added (-1 where the path ended). ``residual_rms``: ``[..., outputs]``, the weighted training
    residual of the chosen fit, ``sqrt(RSS / sum w)``.
    """

    coefficients: torch.Tensor
    selected: torch.Tensor
    loo_error: torch.Tensor
    loo_path: torch.Tensor
    path: torch.Tensor
    residual_rms: torch.Tensor

    @property
    def terms(self) -> torch.Tensor:
        """``[..., outputs]``: how many terms each output's fit kept."""
        return self.selected.sum(-2)


def check_sparsity(max_terms: int | None, patience: int, tolerance: float) -> None:
    """Refuses a bad ``max_terms``, ``patience`` or ``tolerance`` by name (the settings of :func:`select_terms`)."""
    if max_terms is not None and not (isinstance(max_terms, int) and not isinstance(max_terms, bool)
                                      and max_terms >= 1):
        raise ValueError(f"max_terms must be a positive integer or None, got {max_terms!r}")
    if not (isinstance(patience, int) and not isinstance(patience, bool) and patience >= 1):
        raise ValueError(f"patience must be a positive integer, got {patience!r}")
    if not (isinstance(tolerance, (int, float)) and 0 <= tolerance < float("inf")):
        raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance!r}")


def sparse_least_squares(design: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor | None = None,
                         candidates: torch.Tensor | None = None, max_terms: int | None = None,
                         patience: int = 10, tolerance: float = 0.0) -> SparseFit:
    """Sparse least squares on rows at hand: ``design`` ``[..., n, terms]``, ``targets``
    ``[..., n, outputs]``, ``weights`` ``[..., n]`` (None: ones). Every row enters the
    leave-one-out error. See :func:`select_terms` for the rest."""
    if design.shape[:-1] != targets.shape[:-1]:
        raise ValueError(f"design {tuple(design.shape)} and targets {tuple(targets.shape)} disagree on the samples")
    for name, tensor in (("design", design), ("targets", targets)):
        if not torch.isfinite(tensor).all():
            raise ValueError(f"{name} has non-finite values")
    design, targets = design.double(), targets.double()
    if weights is None:
        weights = torch.ones(design.shape[:-1], dtype=design.dtype, device=design.device)
    weights = weights.double()
    samples = int((weights > 0).sum(-1).min())
    if samples < 2:
        raise ValueError(f"a sparse fit needs at least 2 samples of weight > 0 in every problem, got {samples}")
    weighted = design * weights.unsqueeze(-1)
    gram = weighted.transpose(-1, -2) @ design
    moment = weighted.transpose(-1, -2) @ targets
    target_square = (targets.square() * weights.unsqueeze(-1)).sum(-2)
    return select_terms(gram, moment, target_square, weights.sum(-1), design, targets, weights, candidates,
                        max_terms, patience, tolerance)


@torch.no_grad()
def select_terms(gram: torch.Tensor, moment: torch.Tensor, target_square: torch.Tensor, total_weight: torch.Tensor,
                 rows: torch.Tensor, row_targets: torch.Tensor, row_weights: torch.Tensor,
                 candidates: torch.Tensor | None = None, max_terms: int | None = None,
                 patience: int = 10, tolerance: float = 0.0) -> SparseFit:
    """Greedy forward selection per problem and output, stopped at the lowest corrected
    leave-one-out error (see the module docstring), or at the sparsest fit within ``tolerance``
    of it.

    Args:
        gram: ``[..., terms, terms]``, ``X^T W X`` over all the fit's rows (float64).
        moment: ``[..., terms, outputs]``, ``X^T W Y``.
        target_square: ``[..., outputs]``, ``sum w y^2`` (for the training residual).
        total_weight: ``[...]``, ``sum w`` (the ``N`` of Chapelle's correction).
        rows: ``[..., s, terms]``, the design matrix at the rows that estimate the
            leave-one-out error (leading dims broadcast against ``gram``'s).
        row_targets: ``[..., s, outputs]``, their targets; ``row_weights`` ``[..., s]`` their
            weights in the fit.
        candidates: ``[terms]`` or ``[..., terms]`` (bool): the terms that may be selected
            (None: all). Leave out those of an input that never varies: their columns repeat
            lower terms'.
        max_terms: the longest path (None: as long as the data allow: fewer terms than the
            total weight, and none that the selected ones already span).
        patience: the path ends once the error has not improved for this many steps in every
            problem (it rarely comes back down: each term adds variance to the estimate).
        tolerance: keep the sparsest fit on the path whose error is at most ``(1 + tolerance)``
            times the lowest. 0 is Blatman and Sudret's rule (the lowest); the error is flat once
            the terms the outputs depend on are in, and noise decides which of the rest lower it a
            little, so a few percent trades a hair of error for terms that are really there (the
            one-standard-error rule of Hastie, Tibshirani and Friedman in another form).

    Raises:
        ValueError: a bad setting, mismatched shapes, no candidate at all, no rows, or a total
            weight below 2, naming the value.
    """
    check_sparsity(max_terms, patience, tolerance)
    batch, terms, outputs = gram.shape[:-2], gram.shape[-1], moment.shape[-1]
    if gram.shape[-2] != terms or moment.shape[:-1] != gram.shape[:-1]:
        raise ValueError(f"gram {tuple(gram.shape)} and moment {tuple(moment.shape)} disagree on the terms")
    if rows.shape[-1] != terms or rows.shape[-2] != row_targets.shape[-2] or row_targets.shape[-1] != outputs:
        raise ValueError(f"rows {tuple(rows.shape)} and row targets {tuple(row_targets.shape)} disagree with "
                         f"{terms} terms and {outputs} outputs")
    device = gram.device
    problems = math.prod(batch)
    s = rows.shape[-2]
    gram = gram.double().reshape(problems, terms, terms)
    moment = moment.double().reshape(problems, terms, outputs)
    target_square = target_square.double().reshape(problems, outputs)
    total_weight = total_weight.double().reshape(-1).expand(problems)
    rows = rows.double().expand(*batch, s, terms).reshape(problems, s, terms).transpose(-1, -2).contiguous()
    row_targets = row_targets.double().expand(*batch, s, outputs).reshape(problems, s, outputs)
    row_weights = row_weights.double().expand(*batch, s).reshape(problems, s)
    candidates = torch.ones(terms, dtype=torch.bool, device=device) if candidates is None else candidates.bool()
    candidates = candidates.to(device).expand(*batch, terms).reshape(problems, terms)
    if not candidates.any(-1).all():
        raise ValueError("no candidate term to select from in a problem")
    if s < 1:
        raise ValueError("no rows to estimate the leave-one-out error on")
    fitted = int(total_weight.min())
    if fitted < 2:
        raise ValueError(f"a sparse fit needs a total sample weight of at least 2, got {float(total_weight.min())}")
    # Never as many terms as samples; past the rank of the data the dependence test ends the path anyway.
    steps = min(terms, int(candidates.sum(-1).max()), fitted - 1, max_terms or terms)

    # Problems are (problem, output) pairs, solved in chunks that fit the memory budget.
    flat_problem = torch.arange(problems, device=device).repeat_interleave(outputs)
    flat_output = torch.arange(outputs, device=device).repeat(problems)
    per_pair = 8 * (steps * (terms + s + steps) + 4 * terms + 4 * s)
    chunk = max(1, CHUNK_BYTES // per_pair)
    parts = [_greedy_path(gram, moment, target_square, total_weight, rows, row_targets, row_weights, candidates,
                          flat_problem[start:start + chunk], flat_output[start:start + chunk], steps, patience,
                          tolerance)
             for start in range(0, problems * outputs, chunk)]
    coefficients, selected, loo_error, loo_path, path, rms = (torch.cat(p, 0) for p in zip(*parts, strict=True))

    def shaped(t: torch.Tensor, *tail: int) -> torch.Tensor:
        return t.reshape(*batch, outputs, *tail)

    return SparseFit(shaped(coefficients, terms).transpose(-1, -2), shaped(selected, terms).transpose(-1, -2),
                     shaped(loo_error), shaped(loo_path, steps), shaped(path, steps), shaped(rms))


def _greedy_path(gram, moment, target_square, total_weight, rows, row_targets, row_weights, candidates, problem, output,
                 steps: int, patience: int, tolerance: float):
    """One chunk of (problem, output) pairs: their greedy paths, errors and chosen fits.

    With ``A`` the selected terms, ``L`` the Cholesky factor of ``G_AA`` and ``Q = X_A L^-T``
    (orthonormal under the weights), the state carried is ``G[:, A] L^-T`` (each candidate's
    projection on ``Q``), ``L^-1``, ``Q^T W y``, the residual correlations ``X^T W r``, and on the
    leave-one-out rows ``Q`` itself, the residuals and the leverages."""
    pairs, terms, s = len(problem), gram.shape[-1], rows.shape[-1]  # rows: [problems, terms, s]
    device, dtype = gram.device, gram.dtype
    diagonal = gram.diagonal(dim1=-2, dim2=-1)[problem]  # [B, terms]
    residual_correlation = moment[problem, :, output].clone()  # X^T W r, r the residual of the current fit
    available = candidates[problem] & (diagonal > 0)
    projected_norm = torch.zeros(pairs, terms, dtype=dtype, device=device)  # |G_{j,A} L^-T|^2
    # Step-major ([pairs, steps, ...]): the first k steps are a contiguous block, which the products take as it is.
    projections = torch.zeros(pairs, steps, terms, dtype=dtype, device=device)  # (G[:, A] L^-T)^T
    inverse_factor = torch.zeros(pairs, steps, steps, dtype=dtype, device=device)  # L^-1
    along = torch.zeros(pairs, steps, dtype=dtype, device=device)  # Q^T W y
    row_q = torch.zeros(pairs, steps, s, dtype=dtype, device=device)  # Q^T at the rows
    y = row_targets[problem, :, output]
    w = row_weights[problem]
    residual = y.clone()
    leverage = torch.zeros(pairs, s, dtype=dtype, device=device)
    inverse_trace = torch.zeros(pairs, dtype=dtype, device=device)
    n = total_weight[problem]
    variance = y.var(-1, correction=0).clamp_min(torch.finfo(dtype).tiny)
    path = torch.full((pairs, steps), -1, dtype=torch.long, device=device)
    loo_path = torch.full((pairs, steps), torch.inf, dtype=dtype, device=device)
    live = torch.ones(pairs, dtype=torch.bool, device=device)
    best = torch.full((pairs,), torch.inf, dtype=dtype, device=device)
    since_best = torch.zeros(pairs, dtype=torch.long, device=device)
    pair = torch.arange(pairs, device=device)
    for k in range(steps):
        remaining = diagonal - projected_norm
        eligible = available & (remaining > DEPENDENCE_TOLERANCE * diagonal)
        live &= eligible.any(-1)
        if not live.any():
            break
        # OMP: |correlation| with the normalised column (see the module docstring for why not the exact gain).
        gain = torch.where(eligible, residual_correlation.square() / diagonal.clamp_min(torch.finfo(dtype).tiny),
                           torch.full_like(remaining, -1.0))
        j = gain.argmax(-1)
        d = remaining[pair, j].clamp_min(torch.finfo(dtype).tiny).sqrt()
        d = torch.where(live, d, torch.ones_like(d))  # a finished pair adds a zero column
        keep = live.to(dtype)
        known = projections[pair, :k, j]  # l = L^-1 G_{A,j}: [B, k]
        # G is symmetric: its row j is its column j, and a row is contiguous.
        column = (gram[problem, j] - (known.unsqueeze(-2) @ projections[:, :k]).squeeze(-2)) / d.unsqueeze(-1)
        column = column * keep.unsqueeze(-1)
        projections[:, k] = column
        projected_norm += column.square()
        coefficient = residual_correlation[pair, j] / d * keep  # q_k^T W y
        along[:, k] = coefficient
        residual_correlation -= column * coefficient.unsqueeze(-1)
        new_row = -(known.unsqueeze(-2) @ inverse_factor[:, :k, :k]).squeeze(-2) / d.unsqueeze(-1)
        inverse_factor[:, k, :k] = new_row * keep.unsqueeze(-1)
        inverse_factor[:, k, k] = keep / d
        inverse_trace += (new_row.square().sum(-1) + d.pow(-2)) * keep
        q = (rows[problem, j] - (known.unsqueeze(-2) @ row_q[:, :k]).squeeze(-2)) / d.unsqueeze(-1)
        q = q * keep.unsqueeze(-1)
        row_q[:, k] = q
        leverage += w * q.square()
        residual -= q * coefficient.unsqueeze(-1)
        path[:, k] = torch.where(live, j, torch.full_like(j, -1))
        available[pair[live], j[live]] = False
        # Corrected leave-one-out error (Chapelle's factor), relative to the output's variance.
        loo = (residual / (1.0 - leverage).clamp_min(1e-12)).square().mean(-1)
        chapelle = torch.where(n > k + 1, n / (n - (k + 1)).clamp_min(1e-12) * (1.0 + inverse_trace),
                               torch.full_like(n, torch.inf))
        error = torch.where(live, loo * chapelle / variance, torch.full_like(loo, torch.inf))
        loo_path[:, k] = error
        improved = error < best
        best = torch.where(improved, error, best)
        since_best = torch.where(improved, torch.zeros_like(since_best), since_best + 1)
        if not (live & (since_best < patience)).any():
            break
    lowest = loo_path.amin(-1, keepdim=True)
    chosen = (loo_path <= lowest * (1.0 + tolerance)).to(torch.int8).argmax(-1) + 1  # terms kept: a prefix of the path
    within = (torch.arange(steps, device=device) < chosen.unsqueeze(-1)) & (path >= 0)
    # Coefficients on the selected terms: beta_A = L^-T (Q^T W y), on the first `chosen` steps.
    beta = (inverse_factor.transpose(-1, -2) @ (along * within).unsqueeze(-1)).squeeze(-1)
    index = torch.where(within, path, terms)  # steps not kept land in a spare column, dropped after
    coefficients = torch.zeros(pairs, terms + 1, dtype=dtype, device=device).scatter_(1, index, beta * within)
    selected = torch.zeros(pairs, terms + 1, dtype=torch.bool, device=device).scatter_(1, index, within)
    rss = target_square[problem, output] - (along * within).square().sum(-1)
    rms = (rss.clamp_min(0) / n).sqrt()
    loo_error = loo_path.gather(1, (chosen - 1).unsqueeze(-1)).squeeze(-1)
    return coefficients[:, :terms], selected[:, :terms], loo_error, loo_path, path, rms
