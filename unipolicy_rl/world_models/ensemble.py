"""Neural-network ensembles that predict the robot's next state (the MOE surrogates).

All are :class:`~unipolicy_rl.world_models.dynamics.NeuralDynamics`, so the trainer, the world
model and the imagined env take any of them:

* :class:`GaussianEnsemble` (``world_model=moe``, the default): what model-based RL learned
  since the thesis (PETS, MBPO, mbrl-lib). Every member sees the design (l, rho) as an input
  where the env has one, predicts the *change* of the state from the layout's features
  (translation invariant for the walker), as a Gaussian with
  a learned, softly bounded log-variance (trained by Gaussian NLL); the best members on
  validation data are the elites, and imagined trajectories draw their member from them.
* :class:`CellEnsemble` (``world_model=moe_thesis``): the thesis' model ensemble (section
  4.2/5.2): one member per cell of a grid over (l, rho), each a deterministic position
  network and velocity network (2 x 200 ReLU) predicting the next state itself, trained
  by mean squared error on the data of its own cell only; a trajectory uses its design's cell.

The Gaussian head, the elites and the members' draw are :class:`ProbabilisticEnsemble`'s, which
the morphology-conditioned :class:`~unipolicy_rl.world_models.token_ensemble.TokenEnsemble`
shares. All standardise inputs and targets (floored scales); prediction runs each member only on
the rows assigned to it.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from unipolicy_rl.world_models.dynamics import TERMINATED, NeuralDynamics, check_learnable
from unipolicy_rl.world_models.layout import Layout, StateLayout
from unipolicy_rl.world_models.networks import EnsembleMLP

# GaussianEnsemble's targets: the state's change over the step (residual), or the next state itself.
TARGETS = ("change", "next_state")


def run_members(network: nn.Module, x: torch.Tensor, member: torch.Tensor) -> torch.Tensor:
    """``network`` member ``member[i]`` applied to row ``x[i]``, rows grouped by member.

    ``network`` maps ``[members, rows, *row shape]`` to ``[members, rows, *out shape]`` (an
    :class:`EnsembleMLP` has row shape ``[in]``; a token network ``[tokens, in]``). Rows are
    packed into ``[members, max rows per member, *row shape]``, so the cost is about one
    member's pass over the batch rather than every member's.
    """
    members = network.members
    member = member.reshape(-1)
    order = torch.argsort(member, stable=True)
    sorted_member = member[order]
    counts = torch.bincount(sorted_member, minlength=members)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(member.numel(), device=x.device) - starts[sorted_member]
    packed = x.new_zeros(members, int(counts.max()), *x.shape[1:])
    packed[sorted_member, slot] = x[order]
    out = network(packed)
    result = out.new_empty(member.numel(), *out.shape[2:])
    result[order] = out[sorted_member, slot]
    return result


def check_design_grid(layout: Layout, model: str) -> None:
    """Refuses, by name, a model whose members are cells of a grid over the design (l, rho) for a
    layout without that design (a plain env's)."""
    if layout.design_size != 2:
        raise ValueError(f"{model} keeps one member per cell of a grid over the design (l, rho), but the layout "
                         f"{type(layout).__name__} has {layout.design_size} design numbers: use a GaussianEnsemble "
                         f"or a PCEDynamics for an env without a design")


class ProbabilisticEnsemble(NeuralDynamics):
    """What every Gaussian ensemble shares (PETS/MBPO style): ``members`` networks, each output a
    mean and a log-variance softly bounded by learned limits, trained by Gaussian NLL; the
    ``elites`` best members on validation data predict imagined trajectories.

    Args:
        layout: the state the model predicts.
        input_size, target_size: sizes of one row of :meth:`inputs` and :meth:`targets` (the last
            dimension: a token model's rows are tokens).
        members: networks in the ensemble (MBPO: 7).
        elites: how many of the best members (validation MSE) imagined trajectories draw from (MBPO: 5).
        min_log_var, max_log_var: initial soft bounds of the predicted log-variance per output;
            the bounds are learned (mbrl-lib starts them at -10 and 0.5), with a small penalty
            on their width so the variance cannot run off where data is thin.
    """

    BOUND_PENALTY = 0.01

    def __init__(self, layout, input_size: int, target_size: int, members: int, elites: int,
                 min_log_var: float, max_log_var: float) -> None:
        if not (isinstance(members, int) and members >= 1):
            raise ValueError(f"members must be a positive integer, got {members!r}")
        if not (isinstance(elites, int) and 1 <= elites <= members):
            raise ValueError(f"elites must be an integer in [1, members={members}], got {elites!r}")
        if not min_log_var < max_log_var:
            raise ValueError(f"min_log_var ({min_log_var!r}) must be below max_log_var ({max_log_var!r})")
        super().__init__(layout, input_size, target_size)
        self.members = members
        self.min_log_var = nn.Parameter(torch.full((target_size,), float(min_log_var)))
        self.max_log_var = nn.Parameter(torch.full((target_size,), float(max_log_var)))
        self.register_buffer("elites", torch.arange(elites))

    def mean_and_log_var(self, output: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A network's raw output ``[..., 2 * targets]`` as the mean and the bounded log-variance."""
        mean, raw = output.chunk(2, dim=-1)
        log_var = self.max_log_var - F.softplus(self.max_log_var - raw)
        log_var = self.min_log_var + F.softplus(log_var - self.min_log_var)
        return mean, log_var

    @staticmethod
    def gaussian_nll(mean: torch.Tensor, log_var: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Gaussian negative log-likelihood per output, without its constant."""
        return ((mean - y) ** 2) * torch.exp(-log_var) + log_var

    def sample_change(self, mean: torch.Tensor, log_var: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """The standardised change a member predicts: its mean, plus its noise unless ``deterministic``."""
        return mean if deterministic else mean + torch.randn_like(mean) * torch.exp(0.5 * log_var)

    def regularization(self):
        return self.BOUND_PENALTY * (self.max_log_var.sum() - self.min_log_var.sum())

    def set_elites(self, validation_error):
        self.elites.copy_(torch.argsort(validation_error)[: self.elites.numel()])

    @property
    def elite_members(self):
        return [int(e) for e in self.elites]

    def draw_members(self, design, generator=None):
        pick = torch.randint(self.elites.numel(), design.shape[:-1], generator=generator, device=design.device)
        return self.elites[pick]


class GaussianEnsemble(ProbabilisticEnsemble):
    """Probabilistic ensemble of state-change predictors (PETS/MBPO style), conditioned on the
    design where the layout has one; optionally with heads for the reward and the termination.

    Args:
        layout: the state the model predicts.
        action_dim: number of actions.
        members, elites, min_log_var, max_log_var: as :class:`ProbabilisticEnsemble`.
        hidden, activation: each member's MLP.
        learn: what the members learn beside the state change, as more outputs of the same
            Gaussian head (mbrl-lib's reward head): ``reward`` (the step's reward) and
            ``terminated`` (1 where the step ended the episode; the prediction's mean above 0.5
            ends an imagined branch, terminated). Each output is standardised on its own, so a
            reward's scale never weighs against the state's. Empty (the walker's): none.
        target: what the state outputs are: ``change`` (the next state minus this one, residual
            as in PETS and MBPO: one step moves a state little, so the change's scale is the
            step's, not the state's) or ``next_state`` (the next state itself; mbrl-lib's
            ``target_is_delta=False``), each standardised on its own either way.
    """

    def __init__(self, layout: Layout, action_dim: int, members: int = 7, elites: int = 5,
                 hidden: Sequence[int] = (200, 200, 200), activation: str = "silu",
                 min_log_var: float = -10.0, max_log_var: float = 0.5, learn: Sequence[str] = (),
                 target: str = "change") -> None:
        if target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS} (what the state outputs are), got {target!r}")
        learned = check_learnable(learn)
        input_size = layout.feature_size + action_dim + layout.design_size
        outputs = layout.size + len(learned)
        super().__init__(layout, input_size, outputs, members, elites, min_log_var, max_log_var)
        self.learned_outputs = learned
        self.residual = target == "change"
        self.network = EnsembleMLP(members, input_size, 2 * outputs, tuple(hidden), activation)

    def inputs(self, state, action, design):
        return torch.cat([self.layout.features(state), self.layout.scaled_action(action), design], dim=-1)

    def targets(self, state, next_state):
        return next_state - state if self.residual else next_state

    def training_loss(self, x, y):
        return self.gaussian_nll(*self.mean_and_log_var(self.network(x)), y).mean(dim=-1)

    @torch.no_grad()
    def validation_error(self, x, y):
        mean, _ = self.mean_and_log_var(self.network(x))
        return ((mean - y) ** 2).mean(dim=-1)

    @torch.no_grad()
    def predict(self, state, action, design, member, deterministic=False):
        return self.predict_outputs(state, action, design, member, deterministic)[0]

    @torch.no_grad()
    def predict_outputs(self, state, action, design, member, deterministic=False):
        """``(next state, learned [..., len(learned_outputs)])`` of every row, by its ``member``.

        The learned outputs are drawn as the state is (with the member's noise unless
        ``deterministic``), but for ``terminated``: its mean, the probability's estimate, so a
        branch never ends on noise."""
        x = self.input_norm(self.inputs(state, action, design))
        mean, log_var = self.mean_and_log_var(run_members(self.network, x.reshape(-1, x.shape[-1]), member))
        out = self.target_norm.inverse(self.sample_change(mean, log_var, deterministic))
        size = self.layout.size
        next_state = out[..., :size].reshape(state.shape)
        if self.residual:
            next_state = state + next_state
        learned = out[..., size:]
        if TERMINATED in self.learned_outputs:
            column = size + self.learned_outputs.index(TERMINATED)
            learned = learned.clone()
            norm = self.target_norm
            learned[..., column - size] = mean[..., column] * norm.std[column] + norm.mean[column]
        return next_state, learned.reshape(*state.shape[:-1], len(self.learned_outputs))


class CellEnsemble(NeuralDynamics):
    """The thesis' ensemble: per (l, rho) cell, a position network and a velocity network.

    Args:
        layout: the state the model predicts (the thesis predicts its 18-number observation).
        action_dim: number of actions.
        length_range, density_range: the design ranges the grid covers.
        divisions: cells per axis (thesis: 6, so 36 members).
        hidden, activation: each network (thesis: 2 x 200 ReLU).
    """

    def __init__(self, layout: StateLayout, action_dim: int, length_range: Sequence[float],
                 density_range: Sequence[float], divisions: int = 6, hidden: Sequence[int] = (200, 200),
                 activation: str = "relu") -> None:
        if not (isinstance(divisions, int) and divisions >= 1):
            raise ValueError(f"divisions must be a positive integer, got {divisions!r}")
        check_design_grid(layout, type(self).__name__)
        input_size = layout.size + action_dim + layout.design_size
        super().__init__(layout, input_size, layout.size)
        self.members = divisions**2
        self.divisions = divisions
        self.register_buffer("low", torch.tensor([length_range[0], density_range[0]], dtype=torch.float32))
        self.register_buffer("high", torch.tensor([length_range[1], density_range[1]], dtype=torch.float32))
        self.register_buffer("positions", torch.tensor(layout.position_columns))
        self.register_buffer("velocities", torch.tensor(layout.velocity_columns))
        self.position_network = EnsembleMLP(self.members, input_size, len(layout.position_columns), hidden, activation)
        self.velocity_network = EnsembleMLP(self.members, input_size, len(layout.velocity_columns), hidden, activation)

    def inputs(self, state, action, design):
        return torch.cat([state, self.layout.scaled_action(action), design], dim=-1)

    def targets(self, state, next_state):
        return next_state

    def cell(self, design: torch.Tensor) -> torch.Tensor:
        """The grid cell of each design (designs outside the ranges take the nearest cell)."""
        width = (self.high - self.low).clamp_min(1e-12)
        index = ((design.to(self.low.dtype) - self.low) / width * self.divisions).floor().long()
        index = index.clamp(0, self.divisions - 1)
        return index[..., 0] * self.divisions + index[..., 1]

    def data_members(self, design):
        return self.cell(design)

    @property
    def voting_members(self):
        # A member models its own cell of designs only: comparing every cell's return from the
        # same start states would mix models of different robots, not alternatives of one.
        return None

    def _errors(self, x, y):
        positions = (self.position_network(x) - y[..., self.positions]) ** 2
        velocities = (self.velocity_network(x) - y[..., self.velocities]) ** 2
        # Each network's mean squared error, as the two were fitted apart in the thesis.
        return positions.mean(dim=-1) + velocities.mean(dim=-1)

    def training_loss(self, x, y):
        return self._errors(x, y)

    @torch.no_grad()
    def validation_error(self, x, y):
        return self._errors(x, y)

    def draw_members(self, design, generator=None):
        return self.cell(design)

    @torch.no_grad()
    def predict(self, state, action, design, member, deterministic=False):
        x = self.input_norm(self.inputs(state, action, design)).reshape(-1, self.input_norm.mean.numel())
        out = x.new_empty(x.shape[0], self.layout.size)
        out[:, self.positions] = run_members(self.position_network, x, member)
        out[:, self.velocities] = run_members(self.velocity_network, x, member)
        return self.target_norm.inverse(out).reshape(state.shape)
