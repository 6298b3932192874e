"""The adaptive sparse one-step PCE (``world_model=pce_sparse``): per output, the terms the data support.

:class:`~unipolicy_rl.world_models.PCEDynamics` fits a fixed basis (order 3) by least squares:
every output gets every term the data can determine, the terms no output depends on add only
variance, and the bootstrap members, sharing the basis, share its bias. Here the candidate basis
is larger (order 5 by default, hyperbolic truncation) and each output of each member keeps the
terms that lower its corrected leave-one-out error
(:func:`~unipolicy_rl.polynomial_chaos.select_terms`; Blatman and Sudret 2011), so the fit grows
with the data on its own (no oversampling rule) and members disagree where the data are thin.
"""

from __future__ import annotations

import time

import torch
from tensordict import TensorDictBase

from unipolicy_rl.polynomial_chaos.sparse import check_sparsity, select_terms
from unipolicy_rl.world_models.layout import StateLayout
from unipolicy_rl.world_models.pce.dynamics import PCEDynamics
from unipolicy_rl.world_models.trainer import FitReport


class SparsePCEDynamics(PCEDynamics):
    """State change as an adaptive sparse Legendre PCE in (features, actions, design); ``members``
    fits on bootstrap resamples of whole episodes, each with its own terms.

    Inputs, ranges, clamps and prediction are :class:`PCEDynamics`'s (its docstring says why);
    the candidate basis is built the same way, only larger. The fit (:meth:`fit`):

    1. every member's normal equations over all candidates, in one pass over the training rows,
       with the member's resample of whole episodes (:class:`~unipolicy_rl.world_models.pce.dynamics.EpisodeBootstrap`:
       member 0 the plain sample, the others Poisson(1) draws of groups of whole episodes);
    2. per member and output, orthogonal matching pursuit on those normal equations, stopped at
       the lowest corrected leave-one-out error (or the sparsest fit within ``tolerance`` of it),
       the error estimated on ``loo_samples`` random training rows (all of them when fewer);
    3. the terms of an input that never varies in the training data are no candidates.

    ``fitted_terms`` is the number of candidate terms any member or output kept; the report's
    extras add the mean number per output (``mean_terms``) and the mean corrected leave-one-out
    error of member 0 (``loo_error``, relative to each output's variance).

    Args:
        layout: the state the model predicts.
        action_dim: number of actions.
        order: highest polynomial degree of one input in the candidate basis.
        truncation: ``total_degree`` or ``hyperbolic`` (q-norm ``q``).
        q: the q-norm of ``hyperbolic`` truncation, in (0, 1]; 0.5 at order 5 keeps every
            univariate degree up to 5 and the products of two linear terms.
        max_interaction: most inputs in one term.
        interactions: ``all``, or ``controls`` (a term with two or more inputs must contain an
            action or a design input).
        members: fits on episode-bootstrap resamples (1: the plain fit only).
        margin: share of each input's data range added on both sides of it.
        max_terms: the most terms one output keeps (None: as many as the error asks for).
        patience: the greedy path ends once the error has not improved for this many terms.
        tolerance: keep the sparsest fit within this share of the lowest error on the path.
        loo_samples: training rows that estimate the leave-one-out error (an unbiased subsample
            when there are more); their cost grows with this, the normal equations' does not.
        chunk_size: rows of the design matrix built at once while fitting (memory bound).
        lags: previous steps whose state change and action are candidate inputs too (PC-NARX,
            :mod:`~unipolicy_rl.world_models.pce.lags`); 0: none.
        elite_tolerance: as :class:`PCEDynamics`'s (None: imagined branches draw every member).
    """

    def __init__(self, layout: StateLayout, action_dim: int, order: int = 5, truncation: str = "hyperbolic",
                 q: float = 0.5, max_interaction: int | None = 2, interactions: str = "controls", members: int = 3,
                 margin: float = 0.1, max_terms: int | None = 200, patience: int = 10, tolerance: float = 0.0,
                 loo_samples: int = 4096, chunk_size: int = 16384, lags: int = 0,
                 elite_tolerance: float | None = 1.5) -> None:
        check_sparsity(max_terms, patience, tolerance)
        if not (isinstance(loo_samples, int) and not isinstance(loo_samples, bool) and loo_samples >= 2):
            raise ValueError(f"loo_samples must be an integer >= 2, got {loo_samples!r}")
        super().__init__(layout, action_dim, order, truncation, q, max_interaction, interactions, members, margin,
                         ridge=0.0, chunk_size=chunk_size, lags=lags, elite_tolerance=elite_tolerance)
        self.max_terms, self.patience, self.tolerance, self.loo_samples = max_terms, patience, tolerance, loo_samples

    @torch.no_grad()
    def fit(self, transitions: TensorDictBase, train: torch.Tensor, validation: torch.Tensor, oversampling: float,
            generator: torch.Generator | None = None) -> FitReport:
        """Fits in place (see the class docstring); ``oversampling`` is not used: the
        leave-one-out error decides how many terms the data support."""
        started = time.perf_counter()
        train, validation = train.to(self.device), validation.to(self.device)
        inputs, targets, next_state = self.regression_data(transitions)
        candidates = self.candidates(inputs[train])
        self.set_data_ranges(inputs[train], targets[train], next_state[train])
        bootstrap = self.episode_bootstrap(transitions, train, generator)
        every = torch.arange(self.terms, device=self.device)
        gram, moment, square = self.normal_equations(inputs[train], targets[train], bootstrap, every)
        picked = torch.randperm(len(train), generator=generator)[: self.loo_samples].to(self.device)
        rows = self.design_matrix(inputs[train[picked]])
        fit = select_terms(gram, moment, square, bootstrap.total().double(), rows, targets[train[picked]],
                           bootstrap.weights(picked), candidates, self.max_terms, self.patience, self.tolerance)
        self.coefficients.copy_(fit.coefficients.float())
        self.fitted_terms.fill_(int(fit.selected.any(-1).any(0).sum()))
        self.residual_std.copy_(fit.residual_rms.float())
        error = self.validation_error(inputs[validation], targets[validation], targets[train])
        self.set_elites(error)
        scale = targets[train].var(0, correction=0).clamp_min(1e-12)
        train_error = float((fit.residual_rms[0].float().pow(2) / scale).mean())
        return FitReport(1, train_error, error, [int(e) for e in self.elites], 0, time.perf_counter() - started,
                         extras={"elites": int(self.elite_mask.sum()), "mean_terms": float(fit.terms.float().mean()),
                                 "loo_error": float(fit.loo_error[0].mean())})
