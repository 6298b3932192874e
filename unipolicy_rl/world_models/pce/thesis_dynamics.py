"""The thesis' ME-PCE as a world model (``world_model=pce_thesis``): its dynamics and its trainer.

:class:`~unipolicy_rl.polynomial_chaos.ThesisMEPCE` predicts the state at step ``t`` from the
design and the last ``T`` actions, not from the current state. An imagined env steps a state,
so the state a trajectory carries here is the robot's followed by a memory: the step within
the episode and the last ``T - 1`` actions. With the action being taken that is exactly the
ME-PCE's input for the next step; the next memory is the step plus one and the window moved
on. Real data get the same memory from their episodes (:meth:`ThesisPCEDynamics.memory_of`),
so imagination can start at an episode's start (the thesis' whole imagined episodes) or at any
buffered state.

The thesis fitted its expansion to uniformly random actions on 4,900 problems at once; a run
collects far fewer episodes than its 7 x 7 elements at order 3 need (680 per element). The
fit lets the data decide, as :meth:`~unipolicy_rl.world_models.PCEDynamics.fit` does: each
element and step fits the first ``count / oversampling`` terms in order of total degree (the
constant, then the linear terms, ...), and an element no episode visited predicts the mean
state of its step over all elements. docs/results.md ("Polynomial chaos") measures what that
gives.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import replace

import torch
from tensordict import TensorDictBase
from torch import nn

from unipolicy_rl.polynomial_chaos.basis import Basis
from unipolicy_rl.polynomial_chaos.thesis import ThesisMEPCE, pack_by_element
from unipolicy_rl.world_models.ensemble import check_design_grid
from unipolicy_rl.world_models.layout import StateLayout
from unipolicy_rl.world_models.pce.dynamics import drop_unused_standardizers
from unipolicy_rl.world_models.trainer import TRANSITION_KEYS, FitReport


class ThesisPCEDynamics(nn.Module):
    """Per-step, per-element Legendre PCE of the robot's state in (l, rho, the last ``window`` actions).

    One deterministic model (``members == 1``): the elements are chosen by the design, not
    drawn. The coefficients (``[horizon, elements, terms, outputs]``; 240 MB at the thesis'
    sizes with the 18-number state) are refitted from the replay buffer at every epoch, so
    they are left out of checkpoints (a resumed run refits before it imagines).

    Args:
        layout: the robot's state the model predicts (its memory columns are added here).
        action_dim: number of actions.
        length_range, density_range: the design box the element grid covers.
        horizon: steps in an episode (one expansion per step); later steps reuse the last one.
        order, truncation, q: the basis (thesis: order 3, total degree).
        divisions: elements per design axis (thesis: 7).
        window: actions in the expansion (thesis: T = 3).
        ridge: Tikhonov term on the normal equations, per sample of an element.
    """

    members = 1

    def __init__(self, layout: StateLayout, action_dim: int, length_range: Sequence[float],
                 density_range: Sequence[float], horizon: int = 100, order: int = 3, truncation: str = "total_degree",
                 q: float = 1.0, divisions: int = 7, window: int = 3, ridge: float = 1e-6) -> None:
        if not (isinstance(horizon, int) and horizon >= 1):
            raise ValueError(f"horizon must be a positive integer (steps per episode), got {horizon!r}")
        if not ridge >= 0:
            raise ValueError(f"ridge must be >= 0, got {ridge!r}")
        check_design_grid(layout, type(self).__name__)
        pce = ThesisMEPCE(length_range, density_range, action_dim, order, truncation, q, divisions, window,
                          reduction="none", ridge=ridge)
        layout = replace(layout, memory_size=1 + action_dim * (window - 1))
        super().__init__()
        self.layout = layout
        self.pce = pce
        self.action_dim, self.window, self.horizon = action_dim, window, horizon
        self.register_buffer("coefficients", torch.zeros(horizon, pce.elements, pce.terms, layout.robot_size),
                             persistent=False)
        self.register_buffer("elites", torch.zeros(1, dtype=torch.long))
        self.fitted_terms = pce.terms  # the leading terms any element fitted (the rest are zero)
        self._bases: dict[int, Basis] = {pce.terms: pce.basis}
        self._register_load_state_dict_pre_hook(drop_unused_standardizers)

    @property
    def terms(self) -> int:
        return self.pce.terms

    def leading_basis(self, terms: int) -> Basis:
        """The first ``terms`` terms of the basis (in order of total degree)."""
        if terms not in self._bases:
            self._bases[terms] = Basis(self.pce.basis.indices[:terms])
        return self._bases[terms]

    # -- the memory ---------------------------------------------------------------------
    def memory_of(self, batch):
        """Step and last ``window - 1`` actions before and after each step of whole episodes ``[robots, steps]``
        (actions before the episode start are zeros, as in the expansion)."""
        actions = self.layout.scaled_action(batch.get("action")).float()
        robots, steps = actions.shape[:2]
        padded = torch.cat([actions.new_zeros(robots, self.window - 1, self.action_dim), actions], dim=1)
        # windows[:, s] = actions s - T + 1 .. s (the last T - 1 before step s, then the one at s)
        windows = padded.unfold(1, self.window, 1).transpose(-1, -2)
        step = torch.arange(steps, dtype=torch.float32).reshape(1, steps, 1).expand(robots, steps, 1)
        before = torch.cat([step, windows[..., :-1, :].flatten(-2)], dim=-1)
        after = torch.cat([step + 1, windows[..., 1:, :].flatten(-2)], dim=-1)
        return before, after

    def _step_and_window(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The step index of each state (clamped to the fitted horizon) and its action window ``[N, T, a]``."""
        robot = self.layout.robot_size
        step = state[..., robot].round().long().clamp(0, self.horizon - 1)
        past = state[..., robot + 1:].unflatten(-1, (self.window - 1, self.action_dim))
        return step, torch.cat([past, self.layout.scaled_action(action).unsqueeze(-2).to(past.dtype)], dim=-2)

    def _inputs(self, design: torch.Tensor, window: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each row's element and its PCE input (design within the element, then the window), in [-1, 1]."""
        # Designs outside the grid take the nearest element (a DE design on its edge, say).
        design = torch.maximum(torch.minimum(design.double(), self.pce.high.to(design.device)),
                               self.pce.low.to(design.device))
        element, local = self.pce.element(design)
        return element, torch.cat([local.float(), window.flatten(-2).float()], dim=-1)

    # -- the Dynamics interface -----------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.coefficients.device

    @property
    def voting_members(self) -> torch.Tensor:
        # One model (its elements are chosen by the design, not drawn): ME-TRPO's rule then asks
        # whether the policy's return under it still improves.
        return torch.zeros(1, dtype=torch.long, device=self.device)

    def targets(self, state, next_state):
        return next_state[..., :self.layout.robot_size]

    def draw_members(self, design, generator=None):
        return torch.zeros(design.shape[:-1], dtype=torch.long, device=design.device)

    @torch.no_grad()
    def predict(self, state, action, design, member, deterministic=False, chunk_size: int = 4096):
        shape = state.shape
        state, action = state.reshape(-1, shape[-1]), action.reshape(-1, action.shape[-1])
        design = design.reshape(-1, 2)
        step, window = self._step_and_window(state, action)
        element, x = self._inputs(design, window)
        basis, terms = self.leading_basis(self.fitted_terms), self.fitted_terms
        robot = torch.cat([
            # Each row's own coefficients ([rows, terms, outputs]): chunked, as they are gathered per row.
            (basis(x[rows]).unsqueeze(-2) @ self.coefficients[step[rows], element[rows], :terms]).squeeze(-2)
            for rows in torch.arange(len(x)).split(chunk_size)
        ]) if len(x) else state.new_zeros(0, self.layout.robot_size)
        memory = torch.cat([(step + 1).unsqueeze(-1).to(state.dtype), window[..., 1:, :].flatten(-2)], dim=-1)
        return torch.cat([robot, memory], dim=-1).reshape(shape)

    @torch.no_grad()
    def fit(self, transitions: TensorDictBase, train: torch.Tensor, validation: torch.Tensor, oversampling: float,
            generator: torch.Generator | None = None) -> FitReport:
        """Least squares on ``transitions``' rows ``train``, scored on rows ``validation``.

        Every transition is one sample of the expansion of its step (the state after the action,
        from the design and the action window); per step, all elements are solved at once
        (:meth:`ThesisMEPCE.solve_step`). Each element fits the first ``count / oversampling``
        terms of the basis (in order of total degree) that its training samples at that step can
        determine. Held-out transitions give the validation error: the standardised MSE of the
        predicted state, which for this model is its open-loop error, since it never reads the
        state it predicts from.
        """
        started = time.perf_counter()
        # Fitted on the CPU (small per-step solves, index bookkeeping); the coefficients then go to the device.
        state, action, design, next_state = (transitions.get(key).float().cpu() for key in TRANSITION_KEYS)
        step, window = self._step_and_window(state, action)
        element, x = self._inputs(design, window)
        y = self.targets(state, next_state)
        train, validation = train.cpu(), validation.cpu()
        pce, elements = self.pce, self.pce.elements
        coefficients = torch.zeros_like(self.coefficients, device="cpu")
        visited = torch.zeros(elements, dtype=torch.bool)
        widest, fallbacks = 1, 0
        for s in range(self.horizon):
            rows = train[step[train] == s]
            if len(rows) == 0:
                continue
            packed, weight, counts = pack_by_element(element[rows], elements)
            visited |= counts > 0
            # Per element, the terms its samples can determine; the batch solves the widest of them.
            fitted = torch.clamp((counts / oversampling).floor().long(), 0, pce.terms)
            width = max(1, int(fitted.max()))
            inactive = torch.arange(width).unsqueeze(0) >= fitted.unsqueeze(1)
            # Terms of an input an element's samples never varied (an action held at its bound)
            # repeat the constant: they are left out, as PCEDynamics.fit leaves out locked joints.
            inputs = x[rows][packed]
            valid = weight.unsqueeze(-1) > 0
            spread = (torch.where(valid, inputs, -math.inf).amax(1) - torch.where(valid, inputs, math.inf).amin(1))
            constant = spread <= 1e-9  # [elements, inputs]
            basis = self.leading_basis(width)
            inactive |= (constant.unsqueeze(1) & (basis.indices > 0).unsqueeze(0)).any(-1)
            widest = max(widest, width)
            # In float64: the problems are small, and a policy's data are far from the uniform law the basis is
            # orthogonal under, so their Gram matrices are not the near-identity the float32 fit relies on.
            xt = basis.transposed(inputs.double())
            c, diagnostics = pce.solve_step(xt, y[rows][packed].double(), weight.double(), counts, s + 1, inactive,
                                            fallback=True)
            fallbacks += diagnostics.fallbacks
            coefficients[s, :, :width] = c
            # An element with too few samples for even the constant predicts the step's mean state
            # (the constant term of the orthonormal basis is 1).
            coefficients[s, fitted == 0, 0] = y[rows].mean(0)
        self.coefficients.copy_(coefficients)
        self.fitted_terms = widest
        # ---- validation: standardised MSE of the held-out states
        scale = y[train].var(0, correction=0).clamp_min(1e-12)

        def error_on(rows: torch.Tensor) -> torch.Tensor:
            predicted = self.predict(*(t[rows].to(self.device) for t in (state, action, design)), None).cpu()
            return ((predicted[:, :self.layout.robot_size] - y[rows]).pow(2) / scale).mean()

        error, train_error = error_on(validation), float(error_on(train))
        error = error if torch.isfinite(error) else torch.tensor(math.inf)
        return FitReport(1, train_error, error.reshape(1), [0], int((~visited).sum()), time.perf_counter() - started,
                         extras={"solve_fallbacks": fallbacks})

