"""A TorchRL replay buffer's state without its empty capacity: checkpoints sized by what was stored.

``ReplayBuffer.state_dict()`` of a ``LazyTensorStorage`` holds the whole preallocated storage:
a world model's 200,000-transition buffer after 10 real epochs writes 167 MB of zeros to every
checkpoint, and an off-policy learner's million-transition buffer more. Here the storage's
tensors are cut to the rows written (``_len``) when saved and padded back to the capacity when
loaded, so the loaded buffer is the saved one row for row, cursor and all (a resume stays
exact), and a checkpoint of the full storage, as older runs wrote, loads unchanged.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import ReplayBuffer


def compact_state(buffer: ReplayBuffer) -> dict:
    """``buffer.state_dict()`` with each storage tensor cut to its written rows."""
    state = buffer.state_dict()
    storage = state["_storage"]
    rows = storage.get("_len", 0)
    if isinstance(storage.get("_storage"), dict):
        storage["_storage"] = {key: value[:rows].clone() for key, value in storage["_storage"].items()}
    return state


def load_compact_state(buffer: ReplayBuffer, state: dict) -> None:
    """Loads a :func:`compact_state` (or a full ``state_dict``) into ``buffer``, its storage padded
    with zero rows to the buffer's capacity.

    The saved rows are written first, so the storage takes its shape from them ``[capacity]``
    before the state is copied in (TorchRL's own load into an empty storage infers a batch size,
    which it cannot for nested keys such as ``("next", "reward")``)."""
    storage = state["_storage"]
    capacity = buffer._storage.max_size
    tensors = storage.get("_storage")
    if isinstance(tensors, dict) and tensors:
        written = storage.get("_len", 0)
        if any(value.shape[0] > capacity for value in tensors.values()):
            raise ValueError(f"the saved replay buffer holds more rows than this buffer's capacity ({capacity}): "
                             f"was it saved with a larger buffer_capacity?")
        if written:
            buffer.extend(TensorDict({key: value[:written] for key, value in tensors.items()},
                                     batch_size=[written]).unflatten_keys("."))
        padded = {}
        for key, value in tensors.items():
            full = torch.zeros((capacity, *value.shape[1:]), dtype=value.dtype, device=value.device)
            full[: value.shape[0]] = value
            padded[key] = full
        # Nested, as the storage now is (a flat "next.reward" would not match its ("next", "reward")).
        nested = TensorDict(padded, batch_size=[capacity]).unflatten_keys(".").to_dict()
        state = {**state, "_storage": {**storage, "_storage": nested}}
    buffer.load_state_dict(state)
