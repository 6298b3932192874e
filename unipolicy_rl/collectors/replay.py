"""The real transitions a world model is fitted on: a FIFO replay buffer in the model's view.

Each real batch (``[envs, steps]``) becomes one row per real step: the model's state before
and after (the env's state in the model's layout, e.g. the robot's part of the walker's ``full``
state or a plain env's observation, plus the model's memory columns where it has any; for
grammar robots, their link tokens), the action as the env applied it (the layout's
``applied_action``), the design (no numbers for an env without one), the keys of the robot's
build where the model has any (a grammar robot's masks, parents and morphology, which an
imagined branch from that state carries), the step's reward and termination where the model
learns them, whether the step began an episode (read off TorchRL's markers:
:mod:`~unipolicy_rl.world_models.episodes`), and the epoch it was collected in. Steps the
physics faulted on (``physics_fault``, where the env reports it) are left out: their next state
is a repeat, not physics.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer

from unipolicy_rl.collectors.buffer_state import compact_state, load_compact_state
from unipolicy_rl.world_models.dynamics import learned_outputs
from unipolicy_rl.world_models.episodes import episode_starts, last_trajectory_ids
from unipolicy_rl.world_models.trainer import EPISODE_START

COLLECTED_IN = "collected_in"  # the real epoch a buffered transition came from (1 = the first)

StateView = Callable[[torch.Tensor], torch.Tensor]
MemoryOf = Callable[[TensorDictBase], "tuple[torch.Tensor, torch.Tensor] | None"]


def transitions(batch: TensorDictBase, state_of: StateView, memory_of: MemoryOf | None = None,
                state_key: str = "state", build_keys: tuple[str, ...] = (), action_of: StateView | None = None,
                learned: tuple[str, ...] = (), previous_ids: torch.Tensor | None = None) -> TensorDict:
    """One row per real step of ``batch`` (``[envs, steps]``) for the model to fit: state,
    action, design, next state, the ``build_keys`` as the step found them, the ``learned``
    outputs' targets (``reward``, ``terminated``: the step's own), and whether the state began an
    episode (``previous_ids``: as :func:`~unipolicy_rl.world_models.episodes.episode_starts`).
    Steps the physics faulted on are left out.

    ``state_of`` maps the env's ``state_key`` entry (the walker's ``full`` state; a grammar
    robot's ``tokens``; a plain env's observation) to the model's state (the layout's
    ``from_full``); ``memory_of`` (a model's :meth:`~unipolicy_rl.world_models.Dynamics.memory_of`)
    gives the memory columns to append to the states before and after each step, or None for a
    model without memory; ``action_of`` maps the policy's action to the one the env applied (the
    layout's ``applied_action``; None: kept as it is)."""
    keys = batch.keys(include_nested=True)
    fault = ("next", "physics_fault")
    keep = ~batch.get(fault).squeeze(-1) if fault in keys else torch.ones(batch.batch_size, dtype=torch.bool)
    start = episode_starts(batch, previous_ids)
    state, next_state = state_of(batch.get(state_key)), state_of(batch.get(("next", state_key)))
    memory = None if memory_of is None else memory_of(batch)
    if memory is not None:
        state, next_state = torch.cat([state, memory[0]], -1), torch.cat([next_state, memory[1]], -1)
    action = batch.get("action")
    # An env without a design: no numbers of it (every model's design input is then empty).
    design = batch.get("design") if "design" in keys else state.new_zeros(*batch.batch_size, 0)
    rows = TensorDict(
        {
            "state": state,
            "action": action if action_of is None else action_of(action),
            "design": design,
            "next_state": next_state,
            EPISODE_START: start,
            **{key: batch.get(key) for key in build_keys},
            **{key: batch.get(("next", key)).reshape(*batch.batch_size, 1) for key in learned},
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
        action_of: the layout's ``applied_action`` (None: actions kept as the policy gave them).
        learned: what the model learns beside the state (``reward``, ``terminated``): kept per step.

    :meth:`for_model` reads all of these off a model.
    """

    def __init__(self, capacity: int, state_of: StateView, memory_of: MemoryOf | None = None,
                 state_key: str = "state", build_keys: tuple[str, ...] = (), action_of: StateView | None = None,
                 learned: tuple[str, ...] = ()) -> None:
        if not (isinstance(capacity, int) and capacity >= 1):
            raise ValueError(f"buffer capacity must be a positive integer, got {capacity!r}")
        self.state_of, self.memory_of, self.action_of = state_of, memory_of, action_of
        self.state_key, self.build_keys, self.learned = state_key, tuple(build_keys), tuple(learned)
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=1)
        # Each env's last trajectory id in the batch before (episode starts across batches); not
        # saved: after a resume, the first batch's first steps count as starts.
        self.last_ids: torch.Tensor | None = None

    @classmethod
    def for_model(cls, capacity: int, model) -> TransitionBuffer:
        """The buffer a :class:`~unipolicy_rl.world_models.Dynamics` fits on: its layout's state,
        keys and applied action, its memory, and what it learns beside the state."""
        layout = model.layout
        return cls(capacity, layout.from_full, model.memory_of, layout.state_key, layout.build_keys,
                   layout.applied_action, learned_outputs(model))

    def __len__(self) -> int:
        return len(self.buffer)

    def extend(self, batch: TensorDictBase, epoch: int) -> TensorDict:
        """Adds a real epoch's batch, each row tagged with ``epoch``; returns the rows added."""
        rows = transitions(batch, self.state_of, self.memory_of, self.state_key, self.build_keys, self.action_of,
                           self.learned, self.last_ids)
        self.last_ids = last_trajectory_ids(batch)
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
