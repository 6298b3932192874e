"""A replay buffer's checkpointed state: cut to its written rows, loaded back row for row."""

from __future__ import annotations

import io

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from unipolicy_rl.collectors.buffer_state import compact_state, load_compact_state

CAPACITY = 500


def rows(first: int, count: int) -> TensorDict:
    values = torch.arange(first, first + count, dtype=torch.float32)
    return TensorDict({"state": values.unsqueeze(-1).expand(count, 32).clone(),
                       "next": {"done": values.unsqueeze(-1) % 2 == 0}}, batch_size=[count])


def filled(count: int) -> ReplayBuffer:
    buffer = ReplayBuffer(storage=LazyTensorStorage(CAPACITY), batch_size=4)
    buffer.extend(rows(0, count))
    return buffer


def saved_bytes(state: dict) -> int:
    file = io.BytesIO()
    torch.save(state, file)
    return file.tell()


@pytest.mark.parametrize("count", [7, CAPACITY + 13])  # part-filled, and wrapped with its cursor mid-storage
def test_a_loaded_buffer_is_the_saved_one_row_for_row_and_writes_where_it_would_have(count):
    original = filled(count)
    state = compact_state(original)
    copy = ReplayBuffer(storage=LazyTensorStorage(CAPACITY), batch_size=4)
    load_compact_state(copy, state)
    assert len(copy) == len(original)
    assert (copy[: len(copy)] == original[: len(original)]).all()
    original.extend(rows(1000, 5))
    copy.extend(rows(1000, 5))
    assert (copy[: len(copy)] == original[: len(original)]).all()


def test_the_saved_state_grows_with_the_rows_written_not_the_capacity():
    small, full = saved_bytes(compact_state(filled(5))), saved_bytes(filled(5).state_dict())
    assert small < full / 10
    assert saved_bytes(compact_state(filled(CAPACITY + 1))) == pytest.approx(full, rel=0.05)


def test_a_full_storage_state_as_older_checkpoints_wrote_it_loads_too():
    original = filled(9)
    copy = ReplayBuffer(storage=LazyTensorStorage(CAPACITY), batch_size=4)
    load_compact_state(copy, original.state_dict())
    assert (copy[: len(copy)] == original[: len(original)]).all()


def test_a_state_larger_than_the_buffer_is_refused_by_name():
    smaller = ReplayBuffer(storage=LazyTensorStorage(CAPACITY // 2), batch_size=4)
    with pytest.raises(ValueError, match="buffer_capacity"):
        load_compact_state(smaller, compact_state(filled(CAPACITY)))
