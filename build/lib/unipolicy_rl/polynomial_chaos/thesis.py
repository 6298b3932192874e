"""The thesis' multi-element PCE (sections 4.1, 5.1; Algorithm 2), fitted in batched solves.

The state at each control step ``t = 1..H`` is a Legendre PCE in the design (l, rho) and the
actions of the last ``window`` steps, ``u_{t-T} .. u_{t-1}`` (``T = window``), one local PCE per
element of a ``divisions x divisions`` grid over (l, rho) (thesis: 7 x 7, order 3, T = 3: with
4 actions, 14 inputs and C(17, 3) = 680 terms). Within its element the design is uniform and
mapped to [-1, 1]; actions are uniform on [-1, 1]. The first ``T - 1`` steps have fewer past
actions: terms of a missing action are held at zero (their Gram rows are replaced by the
identity), so every step and element shares one basis and one batched solve.

Fitting the window's variables directly by least squares is the L2 projection of the state on
the windowed basis, which is what the thesis' reduction step approximates (its eq. 4.9, with
the wrong norms): :meth:`ThesisMEPCE.fit` with ``reduction="projection"`` or ``"variance"``
instead fits the window plus the action that leaves it and reduces with
:func:`~unipolicy_rl.polynomial_chaos.expansion.reduce` (``variance`` keeps the full
variance, as the thesis asks, with the Legendre norms).

This class fits and predicts whole episodes, for uncertainty quantification on its own;
:class:`~unipolicy_rl.world_models.ThesisPCEDynamics` makes it the dynamics of an imagined env
(``world_model=pce_thesis``), carrying the step and the last actions as the state's memory.
"""

from __future__ import annotations

import time

import torch

from unipolicy_rl.polynomial_chaos.basis import Basis, multi_indices
from unipolicy_rl.polynomial_chaos.expansion import REDUCTIONS, reduce
from unipolicy_rl.polynomial_chaos.regression import FitDiagnostics, rank_revealing_lstsq, solve_normal_equations

MAX_NORMAL_EQUATIONS_CONDITION = 1e6


def pack_by_element(element: torch.Tensor, elements: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Samples grouped by element for a batched solve: ``rows [elements, max count]`` (indices
    into the samples), ``weight`` (1, or 0 on padding) of the same shape, and ``counts [elements]``."""
    order = torch.argsort(element, stable=True)
    counts = torch.bincount(element, minlength=elements)
    width = max(1, int(counts.max())) if counts.numel() else 1
    slot = torch.arange(len(order)) - (torch.cumsum(counts, 0) - counts)[element[order]]
    rows = torch.zeros(elements, width, dtype=torch.long)
    weight = torch.zeros(elements, width, dtype=torch.float32)
    rows[element[order], slot] = order
    weight[element[order], slot] = 1.0
    return rows, weight, counts


class ThesisMEPCE:
    """Per-step, per-element PCE of the state in (l, rho, last ``window`` actions).

    Args:
        length_range, density_range: the design box the grid covers.
        action_dim: actions per step (4).
        order, truncation, q: the basis (thesis: order 3, total degree).
        divisions: elements per design axis (thesis: 7).
        window: past actions in the expansion (thesis: T = 3).
        reduction: ``none`` (fit the window directly), ``projection`` or ``variance`` (fit one
            more action, then drop it by the reduction step).
        ridge: Tikhonov term on the normal equations, per sample of an element.
    """

    def __init__(self, length_range, density_range, action_dim: int = 4, order: int = 3,
                 truncation: str = "total_degree", q: float = 1.0, divisions: int = 7, window: int = 3,
                 reduction: str = "none", ridge: float = 0.0) -> None:
        if not (isinstance(divisions, int) and divisions >= 1):
            raise ValueError(f"divisions must be an integer >= 1, got {divisions!r}")
        if not (isinstance(window, int) and window >= 1):
            raise ValueError(f"window must be an integer >= 1, got {window!r}")
        if not ridge >= 0:
            raise ValueError(f"ridge must be >= 0, got {ridge!r}")
        if reduction not in ("none", *REDUCTIONS):
            raise ValueError(f"reduction must be one of {('none', *REDUCTIONS)}, got {reduction!r}")
        # The box is bookkeeping, kept on the CPU (a model built on another device moves it per call).
        self.low = torch.tensor([length_range[0], density_range[0]], dtype=torch.float64, device="cpu")
        self.high = torch.tensor([length_range[1], density_range[1]], dtype=torch.float64, device="cpu")
        if not (self.high > self.low).all():
            raise ValueError(f"design ranges must have low < high, got {length_range!r} and {density_range!r}")
        self.action_dim, self.divisions, self.window, self.reduction, self.ridge = (action_dim, divisions, window,
                                                                                  reduction, ridge)
        self.fit_window = window + (reduction != "none")
        self.fit_basis = Basis(multi_indices(2 + action_dim * self.fit_window, order, truncation, q))
        kept = (self.fit_basis.indices[:, 2:2 + action_dim] == 0).all(1) if reduction != "none" else None
        self.basis = self.fit_basis if kept is None else Basis(self.fit_basis.indices[kept][:, [0, 1, *range(
            2 + action_dim, 2 + action_dim * self.fit_window)]])
        self.coefficients: torch.Tensor | None = None  # [H, elements, terms, outputs]
        self.diagnostics: FitDiagnostics | None = None

    @property
    def elements(self) -> int:
        return self.divisions**2

    @property
    def terms(self) -> int:
        return self.basis.terms

    def element(self, design: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each design's element and its position in it mapped to [-1, 1]^2; a design outside the box is refused."""
        low, high = self.low.to(design.device), self.high.to(design.device)
        u = (design.double() - low) / (high - low)
        if ((u < -1e-9) | (u > 1 + 1e-9) | ~torch.isfinite(u)).any():
            bad = design.reshape(-1, 2)[((u < -1e-9) | (u > 1 + 1e-9) | ~torch.isfinite(u)).reshape(-1, 2).any(1)][0]
            raise ValueError(f"design {bad.tolist()} lies outside the uniform ranges {self.low.tolist()} - "
                             f"{self.high.tolist()}")
        cell = (u * self.divisions).floor().clamp(0, self.divisions - 1)
        local = 2 * (u * self.divisions - cell) - 1
        return (cell[..., 0] * self.divisions + cell[..., 1]).long(), local

    def _inputs(self, local: torch.Tensor, actions: torch.Tensor, t: int, window: int) -> torch.Tensor:
        """``[..., 2 + a * window]``: design in its element, then ``u_{t-window} .. u_{t-1}`` (zeros
        before the start), for ``local [..., 2]`` and ``actions [..., H, a]``."""
        past = actions.new_zeros(*actions.shape[:-2], window, self.action_dim)
        first = max(0, t - window)
        past[..., window - (t - first):, :] = actions[..., first:t, :]
        return torch.cat([local, past.clamp(-1, 1).flatten(-2).to(local.dtype)], dim=-1)

    def _missing_terms(self, basis: Basis, t: int, window: int) -> torch.Tensor:
        """Terms that involve an action slot before the episode start at step ``t``."""
        missing = max(0, window - t) * self.action_dim
        return (basis.indices[:, 2:2 + missing] > 0).any(1)

    @torch.no_grad()
    def fit(self, design: torch.Tensor, actions: torch.Tensor, states: torch.Tensor) -> dict[str, float]:
        """``design [E, 2]`` per episode, ``actions [E, H, a]``, ``states [E, H, outputs]`` (``states[:, t-1]``
        is the state after action ``t - 1``). Returns timing and conditioning figures."""
        started = time.perf_counter()
        element, local = self.element(design)
        rows, weight, counts = pack_by_element(element, self.elements)
        if int(counts.min()) < self.fit_basis.terms:
            raise ValueError(f"underdetermined fit: {self.fit_basis.terms} terms per element but element "
                             f"{int(counts.argmin())} has {int(counts.min())} episodes; collect more episodes "
                             f"or use fewer divisions / a lower order")
        local, actions, states = local[rows].float(), actions[rows].float(), states[rows].float()
        horizon, outputs = states.shape[2], states.shape[3]
        coefficients = torch.empty(horizon, self.elements, self.terms, outputs, dtype=torch.float32)
        conditions, residuals = [], []
        for t in range(1, horizon + 1):
            # The design matrix transposed ([elements, terms, rows]), as Basis.transposed builds it fastest.
            xt = self.fit_basis.transposed(self._inputs(local, actions, t, self.fit_window))
            c, diagnostics = self.solve_step(xt, states[:, :, t - 1], weight, counts, t)
            if self.reduction != "none":
                _, c = reduce(c, self.fit_basis.indices, list(range(2, 2 + self.action_dim)),
                              self.reduction, self.fit_basis.squared_norms())
            coefficients[t - 1] = c
            conditions.append(diagnostics.condition.max())
            residuals.append(diagnostics.residual_rms.mean())
        self.coefficients = coefficients
        return {"seconds": time.perf_counter() - started, "max_condition": float(torch.stack(conditions).max()),
                "mean_residual_rms": float(torch.stack(residuals).mean()), "terms": float(self.terms),
                "elements": float(self.elements), "min_episodes_per_element": float(counts.min())}

    def solve_step(self, xt: torch.Tensor, y: torch.Tensor, weight: torch.Tensor, counts: torch.Tensor, t: int,
                   inactive: torch.Tensor | None = None,
                   fallback: bool = False) -> tuple[torch.Tensor, FitDiagnostics]:
        """Every element's coefficients at step ``t`` from its packed rows, in one batched solve.

        ``xt`` ``[elements, terms, rows]`` (the first ``terms`` of :attr:`fit_basis`), ``y``
        ``[elements, rows, outputs]``, ``weight`` ``[elements, rows]`` (0 on padding), ``counts``
        ``[elements]``. Terms of actions not yet taken at ``t``, and ``inactive`` ``[elements,
        terms]`` ones, get identity rows in the normal equations (each a pseudo-observation
        ``c = 0``), so they solve to zero and every element shares one batched solve. An element
        whose normal equations cannot be factored raises, or with ``fallback`` is solved by
        rank-revealing least squares on its rows (a policy's actions may sit at their bound, so
        some basis columns repeat others) and counted in ``diagnostics.fallbacks``.
        """
        if not bool(weight.all()):
            xt = xt * weight.unsqueeze(1)
            y = y * weight.unsqueeze(-1)
        gram = xt @ xt.transpose(1, 2)
        moment = xt @ y
        pinned = self._missing_terms(self.fit_basis, t, self.fit_window)[:xt.shape[1]].expand(xt.shape[0], -1)
        if inactive is not None:
            pinned = pinned | inactive
        # The ridge is per sample, so its pull is the same whatever an element's share of the data.
        if self.ridge:
            gram.diagonal(dim1=-2, dim2=-1).add_(self.ridge * counts.to(gram.dtype).unsqueeze(-1))
        if pinned.any():  # (most steps of the thesis' fit have none: a pass over every Gram matrix saved)
            gram.masked_fill_(pinned.unsqueeze(-1) | pinned.unsqueeze(-2), 0.0)
            gram.diagonal(dim1=-2, dim2=-1)[pinned] = 1.0
            moment.masked_fill_(pinned.unsqueeze(-1), 0.0)
        # Factored in the precision the Gram matrices were summed in (float32: float64 where that fails). With
        # ``fallback`` in float64, so a singular element shows as one (a float32 factor hides it in rounding).
        factor_dtype = torch.float64 if fallback else gram.dtype
        c, diagnostics = solve_normal_equations(gram, moment, y.pow(2).sum(1), counts + pinned.sum(1),
                                                factor_dtype=factor_dtype)
        if diagnostics.fallbacks and not fallback:
            raise FloatingPointError(f"step {t}: {diagnostics.fallbacks} elements could not be factored "
                                     f"({diagnostics.summary()}); use ridge > 0 or fewer terms")
        if not fallback:
            return c, diagnostics
        # Past this condition of X the normal equations (cond(X)^2 = 1e12) keep under 4 digits in float64.
        unsolved = diagnostics.failed | (diagnostics.condition > MAX_NORMAL_EQUATIONS_CONDITION)
        diagnostics.fallbacks = int(unsolved.sum())
        for element in unsolved.nonzero().flatten().tolist():
            free = ~pinned[element]
            rows = xt[element, free].mT.double()  # weighted already: padding rows are zero
            c[element] = 0.0
            c[element, free] = rank_revealing_lstsq(rows, y[element].double()).to(c.dtype)
        c = c.to(y.dtype)
        return c, diagnostics

    @torch.no_grad()
    def predict(self, design: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``[E, H, outputs]``: the state after each action (designs ``[E, 2]``, actions ``[E, H, a]``)."""
        if self.coefficients is None:
            raise RuntimeError("fit the ME-PCE before predicting")
        element, local = self.element(design)
        out = []
        for t in range(1, self.coefficients.shape[0] + 1):
            x = self.basis(self._inputs(local, actions, t, self.window).float())
            out.append((x.unsqueeze(1) @ self.coefficients[t - 1, element]).squeeze(1))
        return torch.stack(out, 1)

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and variance ``[H, outputs]`` of the state over the uniform design and actions,
        from the coefficients: the elements are equally likely, so the mixture's mean is the mean
        of the local means and its variance the mean of local (variance + mean^2) minus mean^2."""
        if self.coefficients is None:
            raise RuntimeError("fit the ME-PCE first")
        local_mean = self.coefficients[:, :, 0]
        local_variance = (self.coefficients[:, :, 1:].pow(2) * self.basis.squared_norms()[1:].float().reshape(
            1, 1, -1, 1)).sum(2)
        mean = local_mean.mean(1)
        return mean, (local_variance + local_mean.pow(2)).mean(1) - mean.pow(2)
