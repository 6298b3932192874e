"""Where a world model's members disagree about the next state: the measure, the cut it makes,
and the reward penalty it sets.

MACURA (Frauenknecht et al., ICML 2024) ends a model rollout where the model stops trusting
itself: at the step whose prediction the ensemble's members disagree on past a threshold. Here
that is a setting for every world model whose members are alternative models of one robot
(``imagination.disagreement_cut``): an imagined branch ends at the step where its members'
disagreement about the next state passes the threshold, truncated, never terminated, so the
value estimator bootstraps from the critic there as at a branch's last step.

MOPO (Yu et al., NeurIPS 2020) and MOReL (Kidambi et al., NeurIPS 2020) keep a policy from
exploiting a model's errors by lowering the imagined reward where the model is unsure: MOPO
subtracts ``lambda`` times an uncertainty of the step. Here that is
``imagination.disagreement_penalty``: each imagined step's reward less ``weight`` times the same
measure the cut reads (:class:`DisagreementPenalty`, :class:`PenalizedReward`). A branch runs on;
the policy learns that where the members part, the return it was promised is less sure.

The measure, :class:`MemberDisagreement`: every voting member predicts the row's next state with
its mean (``deterministic``); the disagreement is the members' standard deviation (sample, over
members) of that prediction, per output divided by the standard deviation of the real one-step
change of that output in the replay buffer, then averaged over the outputs that change in the
data. Why this and not MACURA's geometric Jensen-Shannon divergence between the members'
Gaussians: every :class:`~unipolicy_rl.world_models.Dynamics` offers a mean prediction, but not
every one a state-dependent predictive variance (the PCEs' noise is one residual spread per
output), and the aleatoric noise is not a sign that the model is wrong where the spread of
the members' means is (it is what the divergence is dominated by when the means differ). All
members start from the same state, so the spread of the next state is the spread of the
predicted change: dividing by the real change's spread makes the figure "a typical step's
change", the same units for every model (the ensemble's own standardised target), so one
threshold means the same for ``moe`` and ``pce``. Outputs that never change in the data (a
locked joint) carry no information and are left out of the average, rather than divided by
a floor that would turn float noise into a large disagreement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn

from unipolicy_rl.world_models.dynamics import Dynamics
from unipolicy_rl.world_models.networks import MIN_STD

# Keys of an imagined step with the cut or the penalty (under "next"; the reset writes zeros).
DISAGREEMENT = "disagreement"  # the members' disagreement about this step's next state
DISAGREEMENT_CUT = "disagreement_cut"  # True where it passed the threshold and ended the branch
DISAGREEMENT_PENALTY = "disagreement_penalty"  # what the penalty took off this step's reward


def check_threshold(threshold: float, name: str = "imagination.disagreement_cut") -> None:
    """Refuses a threshold that is not a positive finite number, by name."""
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not (
            math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"{name} must be a positive number (a disagreement in units of a typical step's "
                         f"change) or null for no cut, got {threshold!r}")


def check_penalty_weight(weight: float, name: str = "imagination.disagreement_penalty") -> None:
    """Refuses a penalty weight that is not a positive finite number, by name."""
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not (math.isfinite(weight) and weight > 0):
        raise ValueError(f"{name} must be a positive number (reward taken off per unit of the members' "
                         f"disagreement) or null for no penalty, got {weight!r}")


# What each setting that reads the members' disagreement does with it (for the refusal below).
USES = {"imagination.disagreement_cut": "cuts branches", "imagination.disagreement_penalty": "lowers the reward"}


def check_members_disagree(model: Dynamics, setting: str = "imagination.disagreement_cut") -> None:
    """Refuses ``setting`` (the cut or the penalty) for a model whose members are not alternatives
    of one robot (one per design cell) or that has a single member: their disagreement would not
    measure the model's error."""
    voters = model.voting_members
    if voters is None or len(voters) < 2:
        why = ("its members model different designs (one per cell), not alternatives of one robot" if voters is None
               else "it has a single member, so there is no disagreement to measure")
        raise ValueError(f"{setting} {USES[setting]} where a model's members disagree, but "
                         f"{type(model).__name__} cannot: {why}; set {setting}=null with it")


def check_scale(scale: torch.Tensor) -> None:
    """Refuses a scale (from :func:`change_scale`) with no output that changes: nothing to measure."""
    if not (scale > 0).any():
        raise ValueError("the disagreement's scale has no output that changes in the data: nothing to measure")


def change_scale(transitions: TensorDictBase, robot_size: int) -> torch.Tensor:
    """``[robot_size]``: the standard deviation of each output's real one-step change in
    ``transitions`` (keys ``state``, ``next_state``); 0 for an output that does not change."""
    change = (transitions.get("next_state") - transitions.get("state"))[..., :robot_size].float()
    std = change.reshape(-1, robot_size).std(0, correction=0)
    return torch.where(std > MIN_STD, std, torch.zeros_like(std))


@dataclass(frozen=True)
class DisagreementCut:
    """A branch ends where the members' disagreement passes ``threshold`` (units of ``scale``,
    each output's typical one-step change, from :func:`change_scale`; 0 = left out)."""

    threshold: float
    scale: torch.Tensor

    def __post_init__(self) -> None:
        check_threshold(self.threshold)
        check_scale(self.scale)


@dataclass(frozen=True)
class DisagreementPenalty:
    """Each imagined step's reward less ``weight`` times the members' disagreement about its next
    state (units of ``scale``, as :class:`DisagreementCut`'s)."""

    weight: float
    scale: torch.Tensor

    def __post_init__(self) -> None:
        check_penalty_weight(self.weight)
        check_scale(self.scale)


class PenalizedReward(nn.Module):
    """``(reward, disagreement) -> (reward - weight * disagreement, the penalty)``.

    A row where a voting member's prediction is not finite disagrees without measure; it is
    charged the largest finite disagreement of its batch (the worst the batch measured), so the
    penalty stays finite and no row gains from a member that blew up."""

    def __init__(self, weight: float) -> None:
        super().__init__()
        check_penalty_weight(weight)
        self.weight = float(weight)

    def forward(self, reward, disagreement):
        finite = torch.isfinite(disagreement)
        worst = disagreement[finite].max() if finite.any() else disagreement.new_zeros(())
        penalty = self.weight * torch.where(finite, disagreement, worst).to(reward.dtype)
        return reward - penalty, penalty


def member_predictions(model: Dynamics, state: torch.Tensor, action: torch.Tensor,
                       design: torch.Tensor) -> torch.Tensor:
    """``[voters, N, size]``: every voting member's mean prediction of every row (``[N, ...]``).

    A model that predicts every member at once from one design matrix (the PCEs) offers
    ``predict_every_member``; any other :class:`Dynamics` is asked once, with its rows repeated
    per voter (an ensemble then runs each member on its own copy, one batched pass)."""
    voters = model.voting_members
    every = getattr(model, "predict_every_member", None)
    if every is not None:
        return every(state, action, design)[voters]
    k, n = len(voters), state.shape[0]
    member = voters.repeat_interleave(n)
    predicted = model.predict(state.repeat(k, 1), action.repeat(k, 1), design.repeat(k, 1), member,
                              deterministic=True)
    return predicted.reshape(k, n, -1)


class MemberDisagreement(nn.Module):
    """``(state, action, design) -> [N, 1]``: the members' disagreement about each row's next state
    (see the module docstring); not finite where a member's prediction is not."""

    def __init__(self, model: Dynamics, scale: torch.Tensor) -> None:
        super().__init__()
        check_members_disagree(model)
        self.model = model
        varying = scale > 0
        self.register_buffer("inverse_scale", torch.where(varying, 1.0 / scale.clamp_min(MIN_STD), 0.0))
        self.outputs = int(varying.sum())

    @torch.no_grad()
    def forward(self, state, action, design=None):
        device = self.model.device
        if design is None:  # a model of an env without a design
            design = state.new_zeros(*state.shape[:-1], 0)
        predicted = member_predictions(self.model, state.to(device), action.to(device), design.to(device))
        return self.of_predictions(predicted).to(state.device)

    def of_predictions(self, predicted: torch.Tensor) -> torch.Tensor:
        """``[N, 1]``: the disagreement of the voting members' predictions ``[voters, N, size]``."""
        spread = predicted[..., :self.inverse_scale.numel()].std(0) * self.inverse_scale.to(predicted.device)
        return spread.sum(-1, keepdim=True) / self.outputs


class CutDoneHead(nn.Module):
    """The done head with the cut: a fault or a disagreement past ``threshold`` ends the branch,
    truncated, never terminated (the real robot would have walked on; the critic bootstraps).
    ``disagreement_cut`` marks the steps the disagreement ended (a faulted step is a fault). With
    a termination (``terminated``), a step that ended the task and did not fault is terminated,
    not cut."""

    def __init__(self, threshold: float) -> None:
        super().__init__()
        check_threshold(threshold)
        self.threshold = threshold

    def forward(self, fault, disagreement, terminated=None):
        # A member that blew up (a disagreement that is not finite) disagrees past any threshold.
        cut = ~(disagreement <= self.threshold) & ~fault
        if terminated is None:
            done = fault | cut
            return done, torch.zeros_like(done), done.clone(), cut
        terminated = terminated.bool() & ~fault
        cut = cut & ~terminated
        truncated = fault | cut
        return terminated | truncated, terminated, truncated, cut


__all__ = [
    "DISAGREEMENT",
    "DISAGREEMENT_CUT",
    "DISAGREEMENT_PENALTY",
    "CutDoneHead",
    "DisagreementCut",
    "DisagreementPenalty",
    "MemberDisagreement",
    "PenalizedReward",
    "change_scale",
    "check_members_disagree",
    "check_penalty_weight",
    "check_threshold",
    "member_predictions",
]
