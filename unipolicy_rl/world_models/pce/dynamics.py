"""The default PCE world model (``world_model=pce``): a one-step transition PCE that owns its fit.

The thesis' PCE (one expansion per time step in the design and a window of actions) degrades
over the episode and cannot follow a gait whose period depends on the design (docs/results.md,
"Polynomial chaos"; the thesis' own conclusion asks for the current state as an input). Here, as PC-NARX does (Mai,
Spiridonakos, Chatzi and Sudret 2016), the dynamics carry the state and the expansion only
has to describe one control step: the *change* of the state as a Legendre PCE in the same
translation-invariant features as :class:`~unipolicy_rl.world_models.GaussianEnsemble`
(:meth:`StateLayout.features`), the actions and the design (l, rho). No action window grows,
so there is no reduction step and no reduction error.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch
from tensordict import TensorDictBase
from torch import nn

from unipolicy_rl.polynomial_chaos.basis import Basis, multi_indices
from unipolicy_rl.polynomial_chaos.regression import solve_normal_equations
from unipolicy_rl.polynomial_chaos.sensitivity import SobolIndices, sobol_indices
from unipolicy_rl.world_models.episodes import episode_starts
from unipolicy_rl.world_models.layout import StateLayout
from unipolicy_rl.world_models.pce.lags import LagMemory, check_lags
from unipolicy_rl.world_models.trainer import EPISODE_START, TRANSITION_KEYS, FitReport

#: Bootstrap groups of whole episodes at most: enough resolution for the members to differ as the
#: data warrant, few enough that each group's products stay efficient matrix products.
BOOTSTRAP_GROUPS = 256

INTERACTIONS = ("all", "controls")

#: The ridge per unit of sample weight a fit retries with when a member's normal equations cannot
#: be factored: from this (or tenfold the configured one), tenfold at a time, up to the largest.
MIN_RETRY_RIDGE, MAX_RIDGE = 1e-8, 1e-2


@dataclass(frozen=True)
class EpisodeBootstrap:
    """The members' resamples of the training rows, by groups of whole episodes.

    The steps of one episode are not independent samples: resampling them one by one would make
    the members agree more than the data warrant, so a member draws whole episodes (Poisson(1)
    times each, member 0 once each). Episodes are gathered, in buffer order, into at most
    :data:`BOOTSTRAP_GROUPS` groups that share a draw, so the fit's cost does not grow with the
    number of members (:meth:`PCEDynamics.normal_equations`).

    Args:
        group: ``[rows]`` the group of each training row, ``0 .. groups - 1``, every group used.
        draws: ``[members, groups]`` how many times each member draws each group.
    """

    group: torch.Tensor
    draws: torch.Tensor

    @property
    def groups(self) -> int:
        return self.draws.shape[1]

    def weights(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """``[members, rows]`` the sample weights of the training rows (of ``rows`` of them)."""
        return self.draws[:, self.group if rows is None else self.group[rows]]

    def rows_per_group(self) -> torch.Tensor:
        return torch.bincount(self.group, minlength=self.groups).to(self.draws.dtype)

    def samples(self) -> torch.Tensor:
        """``[members]`` rows each member sees at least once."""
        return ((self.draws > 0).to(self.draws.dtype) @ self.rows_per_group()).long()

    def total(self) -> torch.Tensor:
        """``[members]`` each member's weight total."""
        return self.draws @ self.rows_per_group()


class PCEDynamics(nn.Module):
    """State change as a sparse Legendre PCE in (features, actions, design); ``members`` bootstrap fits.

    Inputs are mapped to [-1, 1] by ranges taken from the training data at each fit, widened
    by ``margin`` of their width on each side (a uniform law on the data's box, the PCE's
    input measure). At prediction an input outside its range is clamped to it: a polynomial
    extrapolates badly, and an imagined state may drift a little past the data. For the same
    reason the predicted change is clamped to the range of changes in the training data (with
    the same margin): one control step never moves the robot further than the data ever saw.
    Changes within range can still add up, step after step, to velocities no real step ever
    had (the joint rates then pass the env's explosion limit and the branch ends as a fault), so
    the predicted velocities are also clamped to the data's range of velocities, widened by the
    same margin. Positions are not: the robot is meant to walk out of the data's range.

    Why this basis: the inputs are many (96 features, 4 actions and 2 design values for the
    ``full`` state), and a total-degree basis of order 3 in 102 inputs has 187,460 terms. A
    q-norm (hyperbolic) truncation keeps every input's univariate polynomial up to ``order``
    and only low-order interactions (sparsity of effects; Blatman and Sudret 2011), and
    ``interactions="controls"`` keeps only the interactions that involve an action or the
    design: the PD motor's torque is a function of (target - angle), and l and rho scale the
    response to it. The basis is fixed before the data arrive, so all outputs and all members
    share one design matrix and one Gram matrix per member: a closed-form fit over the
    whole buffer costs a few matrix products, where greedy sparse solvers (orthogonal
    matching pursuit, LARS) pick terms per output, one solve per selected term, and must be
    redone at every refit.

    Fit (:meth:`fit`, called by :class:`~unipolicy_rl.world_models.ClosedFormTrainer` with its
    train/validation split): the input ranges are taken from the training part, the normal
    equations of every member are accumulated over row chunks and solved by Cholesky (float64;
    the ridge raised where a member cannot be factored, :meth:`solve_with_ridge`),
    and each member's validation error is the mean over outputs of its MSE divided by the
    output's variance (standardised MSE, as the ensemble's trainer reports); an epoch count of 1
    is reported. The data decide how much of the basis is fitted: the first ``min(terms, n /
    oversampling)`` terms in order of total degree (the constant, then every linear term, ...),
    ``n`` the distinct training rows of the member that sees the fewest,
    the rest kept at zero, so the first epochs (1,000 real transitions) fit a lower-order model
    and no fit is underdetermined. Terms of an input that did not vary in the training data (a
    locked joint's angle and rate) are left out too: on the data they are constant columns,
    copies of the intercept, and would make the normal equations singular.

    Members are bootstrap fits (Poisson(1) draws of whole episodes, member 0 on the plain sample:
    :class:`EpisodeBootstrap`), so imagined trajectories can draw one and ME-TRPO's stopping
    rule can compare them; ``predict`` adds each member's residual noise (per output) unless ``deterministic``.

    Args:
        layout: the state the model predicts.
        action_dim: number of actions.
        order: highest polynomial degree of one input.
        truncation: ``total_degree`` or ``hyperbolic`` (q-norm ``q``).
        q: the q-norm of ``hyperbolic`` truncation, in (0, 1].
        max_interaction: most inputs in one term.
        interactions: ``all``, or ``controls`` (a term with two or more inputs must contain an
            action or a design input).
        members: bootstrap fits (1: the plain least-squares fit).
        margin: share of each input's data range added on both sides of it.
        ridge: Tikhonov term on the normal equations (per sample, so it does not fade as data grow).
        chunk_size: rows of the design matrix built at once while fitting (memory bound).
        lags: previous steps whose state change and action are inputs too (PC-NARX,
            :mod:`~unipolicy_rl.world_models.pce.lags`), carried as memory columns; 0: none.
        elite_tolerance: imagined branches draw their member from the elites, the members whose
            validation error is at most this multiple of the best member's (None: every member).
            A bootstrap member that left out many episodes can extrapolate wildly where the
            others do not (validation errors of 0.43 and 1.57 beside the plain fit's 0.16 were
            seen on a walking policy's buffer); ME-TRPO's vote and the disagreement cut still
            hear every member.
    """

    def __init__(self, layout: StateLayout, action_dim: int, order: int = 3, truncation: str = "hyperbolic",
                 q: float = 0.75, max_interaction: int | None = 2, interactions: str = "controls",
                 members: int = 3, margin: float = 0.1, ridge: float = 1e-6, chunk_size: int = 16384,
                 lags: int = 0, elite_tolerance: float | None = 1.5) -> None:
        check_lags(lags)
        if isinstance(order, bool) or not isinstance(order, int) or order < 1:
            raise ValueError(f"order must be an integer >= 1 (order 0 keeps the constant term alone: a model that "
                             f"ignores every input), got {order!r}")
        if elite_tolerance is not None and (isinstance(elite_tolerance, bool) or not isinstance(
                elite_tolerance, (int, float)) or not elite_tolerance >= 1):
            raise ValueError(f"elite_tolerance must be a number >= 1 (a multiple of the best member's validation "
                             f"error) or null for every member, got {elite_tolerance!r}")
        if not (isinstance(members, int) and members >= 1):
            raise ValueError(f"members must be a positive integer, got {members!r}")
        if interactions not in INTERACTIONS:
            raise ValueError(f"interactions must be one of {INTERACTIONS}, got {interactions!r}")
        if not margin >= 0:
            raise ValueError(f"margin must be >= 0, got {margin!r}")
        if not ridge >= 0:
            raise ValueError(f"ridge must be >= 0, got {ridge!r}")
        if not (isinstance(chunk_size, int) and chunk_size >= 1):
            raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
        lag_memory = LagMemory(lags, layout.robot_size, action_dim)
        if lags:
            layout = replace(layout, memory_size=lag_memory.size)
        # Inputs: the state's features, the actions, the design (l, rho) where the layout has one,
        # then the lagged changes and actions.
        input_size = layout.feature_size + action_dim + layout.design_size + lag_memory.size
        super().__init__()
        self.layout = layout
        self.lag_memory = lag_memory
        indices = multi_indices(input_size, order, truncation, q, max_interaction)
        if interactions == "controls":
            # The lagged inputs are state (what the robot did), not controls.
            controls = torch.zeros(input_size, dtype=torch.bool, device="cpu")
            controls[layout.feature_size:layout.feature_size + action_dim + layout.design_size] = True
            active = indices > 0
            indices = indices[(active.sum(1) <= 1) | (active & controls).any(1)]
        self.basis = Basis(indices)
        self.members = members
        self.margin, self.ridge, self.chunk_size = margin, ridge, chunk_size
        self.elite_tolerance = elite_tolerance
        self.register_buffer("low", -torch.ones(input_size))
        self.register_buffer("high", torch.ones(input_size))
        # The outputs are the robot's state: the memory is shifted, not predicted.
        outputs = layout.robot_size
        self.register_buffer("change_low", -torch.full((outputs,), math.inf))
        self.register_buffer("change_high", torch.full((outputs,), math.inf))
        self.register_buffer("state_low", -torch.full((outputs,), math.inf))  # velocities only; else -inf
        self.register_buffer("state_high", torch.full((outputs,), math.inf))
        self.register_buffer("coefficients", torch.zeros(members, self.basis.terms, outputs))
        self.register_buffer("residual_std", torch.zeros(members, outputs))
        self.register_buffer("elite_mask", torch.ones(members, dtype=torch.bool))
        self.register_buffer("fitted_terms", torch.zeros((), dtype=torch.long))  # how many terms the data fitted
        self._register_load_state_dict_pre_hook(drop_unused_standardizers)
        self._register_load_state_dict_pre_hook(elites_as_mask)

    @property
    def terms(self) -> int:
        return self.basis.terms

    # -- the Dynamics interface -----------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.coefficients.device

    @property
    def voting_members(self) -> torch.Tensor:
        return torch.arange(self.members, device=self.device)

    @property
    def elites(self) -> torch.Tensor:
        """The members imagined branches draw from (see ``elite_tolerance``)."""
        return self.elite_mask.nonzero().squeeze(1)

    def set_elites(self, validation_error: torch.Tensor) -> None:
        """Keeps as elites the members within ``elite_tolerance`` of the best validation error
        (every member without a tolerance, or where no member's error is finite)."""
        finite = torch.isfinite(validation_error)
        if self.elite_tolerance is None or not finite.any():
            self.elite_mask.fill_(True)
            return
        best = validation_error[finite].min()
        self.elite_mask.copy_((finite & (validation_error <= self.elite_tolerance * best)).to(self.elite_mask.device))

    def memory_of(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The lagged changes and actions before and after each step of a real batch (zeros before
        an episode's start; :meth:`LagMemory.of_episodes`), or None without lags."""
        if not self.lag_memory.lags:
            return None
        robot = self.layout.robot_size
        key = self.layout.state_key
        state, next_state = (self.layout.from_full(batch.get(k))[..., :robot].float() for k in (key, ("next", key)))
        action = self.layout.scaled_action(batch.get("action").float())
        return self.lag_memory.of_episodes(state, action, next_state, episode_starts(batch))

    def inputs(self, state, action, design):
        inputs = [self.layout.features(state), self.layout.scaled_action(action), design.to(state.dtype)]
        if self.lag_memory.lags:
            inputs.append(state[..., self.layout.robot_size:])
        return torch.cat(inputs, dim=-1)

    def targets(self, state, next_state):
        """The robot's change over the step (the memory is no output)."""
        robot = self.layout.robot_size
        return next_state[..., :robot] - state[..., :robot]

    @torch.no_grad()
    def set_ranges(self, inputs: torch.Tensor) -> None:
        low, high = inputs.amin(0), inputs.amax(0)
        # A constant input (a locked joint's rate) gets a unit-free width so z stays finite.
        width = (high - low).clamp_min(1e-6)
        self.low.copy_(low - self.margin * width)
        self.high.copy_(high + self.margin * width)

    def design_matrix(self, inputs: torch.Tensor) -> torch.Tensor:
        """``[..., terms]``: the basis at the inputs, each clamped into its range."""
        z = (2.0 * inputs - (self.low + self.high)) / (self.high - self.low)
        return self.basis(z.clamp(-1.0, 1.0))

    def draw_members(self, design, generator=None):
        elites = self.elites
        pick = torch.randint(elites.numel(), design.shape[:-1], generator=generator, device=design.device)
        return elites[pick]

    def every_member_change(self, state: torch.Tensor, action: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """``[rows, members, size]``: every member's mean change of every row (one design matrix for all)."""
        x = self.design_matrix(self.inputs(state, action, design)).reshape(-1, self.terms)
        return (x @ self.coefficients.permute(1, 0, 2).flatten(1)).unflatten(-1, (self.members, -1))

    def clamped(self, state: torch.Tensor, change: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``state + change`` within the data's range of changes and of velocities (see the class
        docstring), with the memory shifted on by the step taken (its change after the clamps) and
        ``action``."""
        robot = self.layout.robot_size
        change = torch.maximum(torch.minimum(change, self.change_high), self.change_low)
        next_state = state[..., :robot] + change
        next_state = torch.maximum(torch.minimum(next_state, self.state_high), self.state_low)
        if not self.lag_memory.lags:
            return next_state
        memory = self.lag_memory.after_step(state[..., robot:], next_state - state[..., :robot],
                                            self.layout.scaled_action(action))
        return torch.cat([next_state, memory], dim=-1)

    @torch.no_grad()
    def predict(self, state, action, design, member, deterministic=False):
        member = member.reshape(-1)
        # Every member's change for every row, then each row's own: cheap next to building x.
        every = self.every_member_change(state, action, design)
        change = every[torch.arange(every.shape[0], device=every.device), member]
        if not deterministic:
            change = change + torch.randn_like(change) * self.residual_std[member]
        return self.clamped(state, change.reshape(*state.shape[:-1], -1), action)

    @torch.no_grad()
    def predict_every_member(self, state: torch.Tensor, action: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """``[members, rows, size]``: every member's mean prediction of every row ``[rows, ...]``
        (what :func:`~unipolicy_rl.world_models.disagreement.member_predictions` asks for)."""
        every = self.every_member_change(state, action, design).transpose(0, 1)
        return self.clamped(state.reshape(1, -1, state.shape[-1]), every, action.reshape(1, -1, action.shape[-1]))

    @torch.no_grad()
    def fit(self, transitions: TensorDictBase, train: torch.Tensor, validation: torch.Tensor, oversampling: float,
            generator: torch.Generator | None = None) -> FitReport:
        """Fits in place on ``transitions`` (keys :data:`~unipolicy_rl.world_models.trainer.TRANSITION_KEYS`):
        rows ``train`` to fit, rows ``validation`` to score (see the class docstring, "Fit")."""
        started = time.perf_counter()
        train, validation = train.to(self.device), validation.to(self.device)
        inputs, targets, next_state = self.regression_data(transitions)
        candidates = self.candidates(inputs[train])
        bootstrap = self.episode_bootstrap(transitions, train, generator)
        samples, total = bootstrap.samples(), bootstrap.total()
        # The member that sees the fewest distinct rows sets the basis: a Poisson draw of whole
        # episodes can leave out a third of the rows and more when the buffer holds few episodes.
        fewest = int(samples.min())
        terms = min(int(candidates.sum()), int(fewest / oversampling))
        if terms < 1:
            raise ValueError(f"need at least {oversampling} training transitions per PCE term, got {fewest} "
                             f"(of {len(train)}) in the member that sees the fewest")
        active = candidates.nonzero().squeeze(1)[:terms]  # by total degree: the constant, the linear terms, ...
        self.set_data_ranges(inputs[train], targets[train], next_state[train])
        gram, moment, square = self.normal_equations(inputs[train], targets[train], bootstrap, active)
        coefficients, diagnostics, ridge = self.solve_with_ridge(gram, moment, square, samples, total)
        self.coefficients.zero_()
        self.coefficients[:, active] = coefficients.float()
        self.fitted_terms.fill_(terms)
        self.residual_std.copy_(diagnostics.residual_rms)
        error = self.validation_error(inputs[validation], targets[validation], targets[train])
        self.set_elites(error)
        scale = targets[train].var(0, correction=0).clamp_min(1e-12)
        train_error = float((diagnostics.residual_rms[0].pow(2) / scale).mean())
        return FitReport(1, train_error, error, [int(e) for e in self.elites], 0, time.perf_counter() - started,
                         extras={"solve_fallbacks": 0, "ridge": ridge, "elites": int(self.elite_mask.sum())})

    # -- what the coefficients tell -------------------------------------------------------
    def input_names(self, body_names: tuple[str, ...] | None = None) -> list[str]:
        """A name per input of the expansion: the state features, ``action<j>``, ``l``, ``rho``, then
        the lagged changes and actions (:meth:`LagMemory.names`)."""
        features = self.layout.feature_names(body_names)
        design = ("l", "rho")[:self.layout.design_size]
        return [*features, *(f"action{j}" for j in range(self.lag_memory.action_dim)), *design,
                *self.lag_memory.names(self.layout.state_names(body_names))]

    @torch.no_grad()
    def sobol_indices(self, member: int = 0) -> SobolIndices:
        """Which inputs drive which outputs: Sobol' indices of each output's one-step change
        ``[outputs, inputs]`` (named by ``layout.state_names()`` and :meth:`input_names`), read
        from ``member``'s coefficients (:func:`~unipolicy_rl.polynomial_chaos.sobol_indices`;
        the basis is orthonormal). They are the fitted expansion's under its input measure:
        every input independent and uniform on its training range (widened by ``margin``), the
        box the PCE is orthogonal on, not the correlated law of the robot's own states."""
        if not (isinstance(member, int) and 0 <= member < self.members):
            raise ValueError(f"member must be an integer in [0, {self.members}), got {member!r}")
        return sobol_indices(self.basis.indices, self.coefficients[member].cpu(), self.basis.squared_norms())

    # -- the parts of a fit, shared with the sparse PCE -------------------------------------
    def regression_data(self, transitions: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(inputs, targets, next states) of every transition, on the model's device."""
        state, action, design, next_state = (transitions.get(key).float().to(self.device) for key in TRANSITION_KEYS)
        return self.inputs(state, action, design), self.targets(state, next_state), next_state

    def candidates(self, inputs: torch.Tensor) -> torch.Tensor:
        """``[terms]`` (bool): the terms of inputs that vary in the training data. An input that
        does not (a locked joint's angle and rate) has constant columns, copies of the intercept."""
        constant = inputs.amax(0) <= inputs.amin(0)
        return ~(self.basis.indices[:, constant.cpu()] > 0).any(1).to(self.device)

    @torch.no_grad()
    def set_data_ranges(self, inputs: torch.Tensor, targets: torch.Tensor, next_state: torch.Tensor) -> None:
        """The input ranges and the clamps on predicted changes and velocities, from the training rows."""
        self.set_ranges(inputs)
        low, high = targets.amin(0), targets.amax(0)
        self.change_low.copy_(low - self.margin * (high - low))
        self.change_high.copy_(high + self.margin * (high - low))
        velocities = torch.tensor(self.layout.velocity_columns, dtype=torch.long, device=self.device)
        low, high = next_state[:, velocities].amin(0), next_state[:, velocities].amax(0)
        self.state_low[velocities] = low - self.margin * (high - low)
        self.state_high[velocities] = high + self.margin * (high - low)

    def episode_bootstrap(self, transitions: TensorDictBase, train: torch.Tensor,
                          generator: torch.Generator | None) -> EpisodeBootstrap:
        """The members' resamples of the ``train`` rows: member 0 the plain sample, the others one
        Poisson(1) draw per group of whole episodes (:class:`EpisodeBootstrap` says why)."""
        if EPISODE_START in transitions.keys():
            episode = transitions.get(EPISODE_START).reshape(-1).long().cumsum(0).to(self.device)
        else:
            episode = torch.arange(transitions.batch_size[0], device=self.device)
        rank = torch.unique(episode[train], return_inverse=True)[1]
        episodes = int(rank.max()) + 1
        groups = min(episodes, BOOTSTRAP_GROUPS)
        group = torch.div(rank * groups, episodes, rounding_mode="floor")
        draws = torch.poisson(torch.ones(self.members, groups), generator=generator).to(self.device)
        draws[0] = 1.0
        rows = torch.bincount(group, minlength=groups).to(draws.dtype)
        # A member that drew (almost) nothing (one or two episodes in the buffer) fits the plain sample.
        draws[((draws > 0).to(draws.dtype) @ rows) < 2] = 1.0
        return EpisodeBootstrap(group, draws)

    def normal_equations(self, inputs: torch.Tensor, targets: torch.Tensor, bootstrap: EpisodeBootstrap,
                         active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each member's ``X^T W X`` ``[members, terms, terms]``, ``X^T W Y`` and ``sum w y^2`` over the
        ``active`` terms (float64), in one pass over the rows (the design matrix is never held whole).

        A member's weight is constant over a bootstrap group, so its sums are the groups' own
        sums weighted by its draws: each group's ``X_g^T X_g`` is computed once, for every member
        at the cost of one (a per-row bootstrap would need one product per member). The
        products run in float32 over one group's rows (a few hundred at most once the buffer
        is large) and each is added to the members' sums in float64: float32 sums over many
        groups lose the positive definiteness of a Gram matrix whose inputs are nearly
        collinear (a walking policy's buffer of 25,000 rows did), and what rounding is left
        :meth:`solve_with_ridge` absorbs."""
        terms, outputs = len(active), targets.shape[-1]
        order = torch.argsort(bootstrap.group, stable=True)
        inputs, targets = inputs[order], targets[order]
        ends = torch.bincount(bootstrap.group, minlength=bootstrap.groups).cumsum(0).tolist()
        gram = torch.zeros(self.members, terms, terms, device=self.device, dtype=torch.float64)
        moment = torch.zeros(self.members, terms, outputs, device=self.device, dtype=torch.float64)
        square = torch.zeros(self.members, outputs, device=self.device, dtype=torch.float64)
        first = 0
        while first < bootstrap.groups:  # a chunk: whole groups, about chunk_size rows
            start = ends[first - 1] if first else 0
            last = first
            while last + 1 < bootstrap.groups and ends[last + 1] - start <= self.chunk_size:
                last += 1
            # Terms first ([terms, rows]), as the basis builds it: selecting terms copies whole rows.
            xt = self.design_matrix(inputs[start:ends[last]]).transpose(-1, -2)[active].float()
            y = targets[start:ends[last]].float()
            draws = bootstrap.draws[:, first:last + 1].double()  # [members, groups of the chunk]
            a = 0
            for index, end in enumerate(ends[first:last + 1]):
                b = end - start
                x, part = xt[:, a:b], y[a:b]
                weight = draws[:, index:index + 1]
                # Every member's share of the group's sums, added in float64 (see the docstring).
                gram.view(self.members, -1).addmm_(weight, (x @ x.T).view(1, -1).double())
                moment.view(self.members, -1).addmm_(weight, (x @ part).view(1, -1).double())
                square += weight * part.double().pow(2).sum(0)
                a = b
            first = last + 1
        return gram, moment, square

    def solve_with_ridge(self, gram: torch.Tensor, moment: torch.Tensor, square: torch.Tensor, samples: torch.Tensor,
                         total: torch.Tensor):
        """(coefficients, diagnostics, the ridge per unit weight used): the normal equations solved by
        Cholesky with ``ridge`` times each member's weight total on the diagonal (so its pull does
        not fade as the buffer grows), raised tenfold at a time, up to :data:`MAX_RIDGE`, while any
        member cannot be factored.

        The robot's features are nearly collinear (the velocities of rigidly joined links are
        linear in a few rates), so a Gram matrix can have eigenvalues at the level of its
        rounding error; which ridge first makes it factorable depends on the data, not on a
        setting a user could know in advance (``model/ridge`` logs the one used)."""
        eye = torch.eye(gram.shape[-1], device=self.device, dtype=gram.dtype)
        ridge = self.ridge
        while True:
            coefficients, diagnostics = solve_normal_equations(gram + ridge * total.reshape(-1, 1, 1) * eye, moment,
                                                               square, samples)
            if not diagnostics.fallbacks:
                return coefficients, diagnostics, ridge
            if ridge >= MAX_RIDGE:
                raise FloatingPointError(f"the PCE's normal equations could not be factored even with a ridge of "
                                         f"{ridge:g} per sample: {diagnostics.summary()}; lower the order")
            ridge = min(MAX_RIDGE, max(10 * ridge, MIN_RETRY_RIDGE))

    def validation_error(self, inputs: torch.Tensor, targets: torch.Tensor,
                         train_targets: torch.Tensor) -> torch.Tensor:
        """Each member's standardised MSE on held-out rows ``[members]`` (CPU; inf where not finite):
        the mean over outputs of the MSE divided by the output's training variance."""
        x = self.design_matrix(inputs)
        predicted = (x @ self.coefficients.permute(1, 0, 2).flatten(1)).unflatten(-1, (self.members, -1))
        scale = train_targets.var(0, correction=0).clamp_min(1e-12)
        error = ((predicted - targets.unsqueeze(1)).pow(2) / scale).mean(dim=(0, 2))
        return torch.where(torch.isfinite(error), error, torch.full_like(error, math.inf)).cpu()


def drop_unused_standardizers(state_dict, prefix, *args) -> None:
    """Checkpoints written before the model stopped carrying the neural models' (unused)
    input/target standardisers still load."""
    for key in [k for k in state_dict if k.startswith((f"{prefix}input_norm.", f"{prefix}target_norm."))]:
        del state_dict[key]


def elites_as_mask(state_dict, prefix, *args) -> None:
    """Checkpoints written when the elites were a list of every member (``elites``) load as a mask
    of every member (``elite_mask``)."""
    old = state_dict.pop(f"{prefix}elites", None)
    if old is not None and f"{prefix}elite_mask" not in state_dict:
        mask = torch.zeros(int(old.max()) + 1 if old.numel() else 0, dtype=torch.bool)
        mask[old] = True
        state_dict[f"{prefix}elite_mask"] = mask
