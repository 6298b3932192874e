"""The real transitions a world model is fitted on: a FIFO replay buffer in the model's view.

Each real epoch's batch (``[robots, steps]`` of whole episodes) becomes one row per real step:
the model's state before and after (the robot's part of the env's ``full`` state, plus the
model's memory columns where it has any; for grammar robots, their link tokens), the action,
the design, the keys of the robot's build where the model has any (a grammar robot's masks,
parents and morphology, which an imagined branch from that state carries), whether the step
began an episode, and the epoch it was collected in. Steps the physics faulted on are left out:
their next state is a repeat, not physics.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer

from unipolicy_rl.collectors.buffer_state import compact_state, load_compact_state
from unipolicy_rl.world_models.trainer import EPISODE_START

COLLECTED_IN = "collected_in"  # the real epoch a buffered transition came from (1 = the first)

StateView = Callable[[torch.Tensor], torch.Tensor]
MemoryOf = Callable[[TensorDictBase], "tuple[torch.Tensor, torch.Tensor] | None"]


def transitions(batch: TensorDictBase, state_of: StateView, memory_of: MemoryOf | None = None,
                state_key: str = "state", build_keys: tuple[str, ...] = ()) -> TensorDict:
    """One row per real step of ``batch`` (``[robots, steps]``) for the model to fit: state,
    action, design, next state, the ``build_keys`` as the step found them, and whether the state
    began an episode. Steps the physics faulted on are left out.

    ``state_of`` maps the env's ``state_key`` entry (the ``full`` state; a grammar robot's
    ``tokens``) to the model's state (the layout's ``from_full``); ``memory_of`` (a model's
    :meth:`~unipolicy_rl.world_models.Dynamics.memory_of`) gives the memory columns to append to
    the states before and after each step, or None for a model without memory."""
    keep = ~batch.get(("next", "physics_fault")).squeeze(-1)
    start = torch.zeros(batch.batch_size, dtype=torch.bool)
    start[..., 0] = True  # every epoch starts every robot from a reset
    state, next_state = state_of(batch.get(state_key)), state_of(batch.get(("next", state_key)))
    memory = None if memory_of is None else memory_of(batch)
    if memory is not None:
        state, next_state = torch.cat([state, memory[0]], -1), torch.cat([next_state, memory[1]], -1)
    rows = TensorDict(
        {
            "state": state,
            "action": batch.get("action").clamp(-1.0, 1.0),
            "design": batch.get("design"),
            "next_state": next_state,
            EPISODE_START: start,
            **{key: batch.get(key) for key in build_keys},
        },
        batch_size=batch.batch_size,
    )
    return rows[keep]


class TransitionBuffer:
    """The last ``capacity`` real transitions (TorchRL ``ReplayBuffer``, FIFO) in a model's view.

    Args:
        capacity: transitions kept.
        state_of: the env's ``state_key`` entry -> the model's state (the layout's ``from_full``).
        memory_of: the model's memory columns of a real batch (``Dynamics.memory_of``).
        state_key, build_keys: the layout's: where the env holds the robot's state, and the keys
            of its build an imagined branch carries (:func:`transitions`).
    """

    def __init__(self, capacity: int, state_of: StateView, memory_of: MemoryOf | None = None,
                 state_key: str = "state", build_keys: tuple[str, ...] = ()) -> None:
        if not (isinstance(capacity, int) and capacity >= 1):
            raise ValueError(f"buffer capacity must be a positive integer, got {capacity!r}")
        self.state_of, self.memory_of = state_of, memory_of
        self.state_key, self.build_keys = state_key, tuple(build_keys)
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=1)

    def __len__(self) -> int:
        return len(self.buffer)

    def extend(self, batch: TensorDictBase, epoch: int) -> TensorDict:
        """Adds a real epoch's batch, each row tagged with ``epoch``; returns the rows added."""
        rows = transitions(batch, self.state_of, self.memory_of, self.state_key, self.build_keys)
        if len(self.buffer) == 0 or COLLECTED_IN in self.buffer[:1].keys():  # (not into an older run's buffer)
            rows.set(COLLECTED_IN, torch.full(rows.batch_size, epoch, dtype=torch.long))
        self.buffer.extend(rows)
        return rows

    def contents(self) -> TensorDictBase:
        """Every buffered transition, oldest first until the buffer wraps (``[N]``)."""
        return self.buffer[: len(self.buffer)]

    def state_dict(self) -> dict:
        return compact_state(self.buffer)

    def load_state_dict(self, state: dict) -> None:
        load_compact_state(self.buffer, state)
