"""How wrong the world model is on the states the current policy just visited, before it fits them.

A fit's validation error is measured on a random share of the buffer it trains on: states of
every past policy, most of which the model has already seen the neighbours of. The question a
model-based run needs answered is another one: on the states the *current* policy reaches (the
ones its imagined updates are about), how good was the model it trained on? The epoch's new real
transitions answer it exactly, once, before they join the buffer and the fit: they are held out
from that model by construction.

Two figures, for any :class:`~unipolicy_rl.world_models.Dynamics`:

* ``fresh_error``: the share of the variance of the real one-step state change the model's mean
  prediction leaves unexplained, averaged over the state's outputs (0: exact; 1: no better than
  predicting the batch's mean change). Unit-free, so models, outputs and epochs compare.
* ``fresh_spread_rank``: the rank correlation, over the new transitions, between the members'
  disagreement and the error of their mean: whether the spread the model reports tracks its
  actual error there (what a cut or a stopping rule on disagreement relies on: the spread is
  the one :mod:`~unipolicy_rl.world_models.disagreement` measures, here in units of the new
  batch's real change). NaN with a single member.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from unipolicy_rl.world_models.disagreement import member_predictions
from unipolicy_rl.world_models.dynamics import Dynamics

# Outputs whose real change varies less than this (in their own units, squared) over the batch
# carry no signal to explain (a joint locked at its limit, a constant memory column).
MIN_VARIANCE = 1e-10


def rank_correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman's rank correlation of two 1-D tensors (ties broken by order)."""
    if a.numel() < 2:
        return float("nan")
    ranks = [torch.argsort(torch.argsort(v)).double() for v in (a, b)]
    ranks = [r - r.mean() for r in ranks]
    denominator = (ranks[0].square().sum() * ranks[1].square().sum()).sqrt()
    return float((ranks[0] * ranks[1]).sum() / denominator) if denominator > 0 else float("nan")


def changing_outputs(change: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The variance of each output's real change over the rows ``[n, outputs]``, and which outputs
    vary (the ones an error share is taken over)."""
    variance = change.var(0, correction=0)
    signal = variance > MIN_VARIANCE
    if not signal.any():
        raise ValueError("the real state changes do not vary over these transitions: there is nothing to explain")
    return variance, signal


def no_change_error(transitions: TensorDictBase, robot_size: int) -> float:
    """The ``fresh_error`` figure of a model that predicts no change, on ``transitions``: per output
    ``E[change^2] / Var(change)``, so 1 plus the squared mean change over its variance. The floor
    any model of these transitions should beat (a drifting output puts it above 1)."""
    rows = transitions.reshape(-1)
    change = (rows.get("next_state") - rows.get("state"))[..., :robot_size].float()
    variance, signal = changing_outputs(change)
    return float((change.square().mean(0)[signal] / variance[signal]).mean())


@torch.no_grad()
def fresh_error(model: Dynamics, transitions: TensorDictBase, prefix: str = "model/") -> dict[str, float]:
    """``{prefix}fresh_error`` and ``{prefix}fresh_spread_rank`` of ``model`` on ``transitions``.

    ``transitions`` are rows in the model's view (keys ``state``, ``action``, ``design``,
    ``next_state``: what :class:`~unipolicy_rl.collectors.replay.TransitionBuffer` stores) that the
    model was not fitted on. Every voting member predicts every row without its noise; a model
    whose members are design cells (no voters) predicts each row with the member that owns it.
    """
    rows = transitions.reshape(-1)
    if rows.batch_size[0] < 2:
        raise ValueError(f"need at least 2 transitions to measure a model's error, got {rows.batch_size[0]}")
    device = model.device
    state, action, design, next_state = (rows.get(key).float().to(device)
                                         for key in ("state", "action", "design", "next_state"))
    if model.voting_members is not None:
        predictions = member_predictions(model, state, action, design) - state  # [members, n, outputs]
    else:
        member = model.draw_members(design).to(device)
        predictions = (model.predict(state, action, design, member, deterministic=True) - state).unsqueeze(0)
    change = next_state - state
    # The robot's outputs only: a model's memory columns (a step count, lagged inputs) are bookkeeping
    # the model shifts on, not predictions (a lagged change would count the same error twice).
    robot = model.layout.robot_size
    predictions, change = predictions[..., :robot], change[..., :robot]
    variance, signal = changing_outputs(change)
    mean_prediction = predictions.mean(0)
    unexplained = (mean_prediction - change).square().mean(0)[signal] / variance[signal]
    scale = variance[signal].sqrt()
    error_per_row = ((mean_prediction - change)[:, signal] / scale).square().mean(1)
    spread_per_row = (predictions[:, :, signal].std(0) / scale).mean(1) if len(predictions) > 1 else None
    return {
        f"{prefix}fresh_error": float(unexplained.mean()),
        f"{prefix}fresh_spread_rank": (rank_correlation(spread_per_row, error_per_row) if spread_per_row is not None
                                       else float("nan")),
    }
