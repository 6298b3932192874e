"""Where episodes begin in a batch of real steps, read off TorchRL's own markers.

A batch ``[rows, steps]`` need not start each row with a reset (a collector's batch continues
the episodes the last one left), and an episode may begin anywhere in a row. Models with memory
(a PC-NARX's lags), the bootstrap by whole episodes and the thesis' episode rollouts need the
starts, so they are read, never assumed, in this order:

* ``is_init`` (TorchRL's ``InitTracker`` transform): True exactly at each episode's first step;
* ``("collector", "traj_ids")`` (any TorchRL collector): a step begins an episode where its
  trajectory id differs from the step before it in its row; for a row's first step, the step
  before is the row's last step of the previous batch (``previous_ids``), and with none known
  (the first batch) the step begins one;
* otherwise, as ``env.rollout`` gives a batch: each row's first step (a rollout starts with a
  reset), and every step after one that ended (``("next", "done")``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

IS_INIT = "is_init"
TRAJECTORY_IDS = ("collector", "traj_ids")


def episode_starts(batch: TensorDictBase, previous_ids: torch.Tensor | None = None) -> torch.Tensor:
    """``batch.batch_size`` (bool): True where a step of ``batch`` (``[rows, steps]`` or ``[steps]``)
    begins an episode (see the module docstring); ``previous_ids``: each row's last trajectory id
    in the batch before, ``batch.batch_size[:-1]``."""
    shape = batch.batch_size
    keys = batch.keys(include_nested=True)
    if IS_INIT in keys:
        return batch.get(IS_INIT).reshape(shape).bool().cpu()
    starts = torch.zeros(shape, dtype=torch.bool)
    if TRAJECTORY_IDS in keys:
        ids = batch.get(TRAJECTORY_IDS).reshape(shape).cpu()
        starts[..., 1:] = ids[..., 1:] != ids[..., :-1]
        starts[..., 0] = True if previous_ids is None else ids[..., 0] != previous_ids.reshape(shape[:-1]).cpu()
        return starts
    starts[..., 0] = True
    if ("next", "done") in keys:
        starts[..., 1:] |= batch.get(("next", "done")).reshape(shape)[..., :-1].bool().cpu()
    return starts


def last_trajectory_ids(batch: TensorDictBase) -> torch.Tensor | None:
    """Each row's trajectory id at its last step (the ``previous_ids`` of the next batch), or None
    for a batch without trajectory ids."""
    if TRAJECTORY_IDS not in batch.keys(include_nested=True):
        return None
    return batch.get(TRAJECTORY_IDS).reshape(batch.batch_size)[..., -1].cpu().clone()
