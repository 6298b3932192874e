"""What every world model's dynamics offer the imagined env and the ME-TRPO rule: :class:`Dynamics`.

Two families implement it. Neural ensembles (:class:`NeuralDynamics` and its subclasses) are
fitted by gradient descent in standardised space by :class:`~unipolicy_rl.world_models.ModelTrainer`,
which only calls the hooks :class:`NeuralDynamics` declares (inputs, targets, losses, elites).
Closed-form models (the polynomial-chaos ones) own their fit: their trainer splits the data and
hands the two parts to the model's ``fit``. Everything downstream (the imagined env, the
stopping rule, accuracy benchmarks) sees only :class:`Dynamics`, as mbrl-lib's wrappers see only
its ``Model`` base.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from torch import nn

from unipolicy_rl.world_models.layout import Layout
from unipolicy_rl.world_models.networks import Standardizer

# What a model may learn beside the next state, one output column each after the state's, named as
# the replay buffer's keys: the step's reward, and whether it ended the episode (1) or not (0).
REWARD, TERMINATED = "reward", "terminated"
LEARNABLE = (REWARD, TERMINATED)


def learned_outputs(model) -> tuple[str, ...]:
    """What ``model`` learns beside the next state (:data:`LEARNABLE`; none for a model that does
    not say, as the polynomial chaos models do not)."""
    return tuple(getattr(model, "learned_outputs", ()))


def check_learnable(learn) -> tuple[str, ...]:
    """``learn`` as a tuple of :data:`LEARNABLE` names in their order, unknown or repeated names refused."""
    names = tuple(learn)
    unknown = [name for name in names if name not in LEARNABLE]
    if unknown or len(set(names)) != len(names):
        raise ValueError(f"learn must name each of {LEARNABLE} at most once, got {list(names)!r}")
    return tuple(name for name in LEARNABLE if name in names)


@runtime_checkable
class Dynamics(Protocol):
    """A batch of ``members`` that predict the robot's next state from ``(state, action, design)``.

    Attributes:
        layout: what the state vector holds (and the policy's view of it).
        members: how many predictors there are (``member`` indices run over ``range(members)``).
    """

    layout: Layout
    members: int

    @property
    def device(self) -> torch.device:
        """Where the model predicts; callers bring their tensors here."""
        ...

    @property
    def voting_members(self) -> torch.Tensor | None:
        """The members ME-TRPO's stopping rule compares a policy on (``[k]`` long), or None where
        members are not alternative models of the same robot (one per design cell), so the rule
        cannot be used with this model."""
        ...

    def draw_members(self, design: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The member that predicts each row (``[N]`` long) for trajectories of these designs."""
        ...

    def predict(self, state: torch.Tensor, action: torch.Tensor, design: torch.Tensor, member: torch.Tensor,
                deterministic: bool = False) -> torch.Tensor:
        """The next state of every row, by its ``member`` (without the model's noise if ``deterministic``)."""
        ...

    def memory_of(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The memory columns (``layout.memory_size``) of the states before and after each step of
        a real batch ``[robots, steps]`` whose rows are whole episodes; None for a model without."""
        ...


class NeuralDynamics(nn.Module):
    """Base of the gradient-trained ensembles: :class:`Dynamics`, plus what their trainer calls.

    The trainer works in standardised space: :meth:`inputs`/:meth:`targets` build the raw
    regression pairs, :meth:`fit_normalizers` fits the standardisers, :meth:`training_loss` and
    :meth:`validation_error` take standardised ``[members, batch, ...]`` tensors and return one
    value per member and sample (``[members, batch]``; the trainer averages them over each
    member's own samples), and :meth:`set_elites` hears each member's validation error.
    """

    layout: Layout
    members: int
    # What the model learns beside the next state (:data:`LEARNABLE`): the trainer appends the
    # transitions' columns of these names to its targets.
    learned_outputs: tuple[str, ...] = ()

    def __init__(self, layout: Layout, input_size: int, target_size: int) -> None:
        super().__init__()
        self.layout = layout
        self.input_norm = Standardizer(input_size)
        self.target_norm = Standardizer(target_size)

    # -- the Dynamics interface ---------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.input_norm.mean.device

    @property
    def voting_members(self) -> torch.Tensor | None:
        return torch.arange(self.members, device=self.device)

    def memory_of(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None

    def draw_members(self, design: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        raise NotImplementedError

    def predict(self, state: torch.Tensor, action: torch.Tensor, design: torch.Tensor, member: torch.Tensor,
                deterministic: bool = False) -> torch.Tensor:
        raise NotImplementedError

    # -- what the trainer calls -----------------------------------------------------------
    def inputs(self, state: torch.Tensor, action: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def targets(self, state: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def fit_normalizers(self, inputs: torch.Tensor, targets: torch.Tensor) -> None:
        self.input_norm.fit(inputs)
        self.target_norm.fit(targets)

    def data_members(self, design: torch.Tensor) -> torch.Tensor | None:
        """The member each training sample belongs to, or None when every member sees all data."""
        return None

    def training_loss(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def validation_error(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def regularization(self) -> torch.Tensor:
        return torch.zeros(())

    def member_parameters(self) -> list[nn.Parameter]:
        """Parameters whose first dimension is the member (kept per member by early stopping)."""
        return [p for p in self.parameters() if p.dim() >= 2 and p.shape[0] == self.members]

    def set_elites(self, validation_error: torch.Tensor) -> None:
        """Called by the trainer with each member's validation error after a fit."""

    @property
    def elite_members(self) -> list[int]:
        """The members imagined trajectories draw from (all, unless a subclass keeps elites)."""
        return list(range(self.members))
