"""MBPO's model refreshes while an epoch is collected (``imagination.refit_every``).

MBPO refits its model every 250 real steps and then fills the learner's model buffer with the
refitted model's branches, rolled out by the current policy. This project's loop fits once per
epoch, after it (1,000 real steps on a gym task): between two fits, the 95% of every minibatch
that comes from the model comes from a model that has not seen the epoch's states, rolled out by
the policy that started the epoch. An off-policy learner that learns while the epoch is collected
(``algo.update_every``) can take MBPO's schedule: :class:`RefitsWithinEpoch` is then the real
collector's ``between_chunks``. Each chunk goes to the learner (its gradient steps); every
``refit_every`` env steps, the chunks since the last refit join the model's buffer, the model is
refitted on the whole buffer and the imagination's batch from the current policy goes to the
learner's model buffer. The fit after the epoch stays the loop's, on the steps since the last
refit within it (:meth:`RefitsWithinEpoch.rest_of_epoch`).

Reproducible as the rest of the loop: the k-th refit of an epoch draws its fit and its branches
from the seeds of (seed, epoch, phase, k), so a run resumed at an epoch's end repeats the
straight one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from unipolicy_rl.seeding import MODEL_FIT, reseed

if TYPE_CHECKING:  # (the factories build the parts and import this module)
    from unipolicy_rl.factories import WorldModelParts


class LearnsWhileCollecting(Protocol):
    """What the refits need of an off-policy learner built for a world model (MBPO)."""

    def update_chunk(self, chunk: TensorDictBase) -> None: ...

    def update(self, batch: TensorDictBase) -> dict[str, float]: ...


class RefitsWithinEpoch:
    """The real collector's ``between_chunks`` for MBPO's refits (see the module docstring).

    Args:
        learner: the off-policy learner (``update_chunk`` takes each real chunk's gradient steps,
            ``update`` stores an imagined batch in its model buffer).
        world: the model, its trainer, the buffer of real transitions it fits on, the imagination.
        policy: what rolls the imagined branches out (the learner's policy).
        seed: the run's seed.
        every: env steps (of each env) from one refit to the next.
        steps_per_epoch: each env's steps in one epoch (a refit at the epoch's end is the loop's).
        as_env_batch: a chunk as the model's buffer takes it (``[envs, steps]``; a gym task's one
            env's chunk is ``[steps]``).
        epoch: the epoch the next chunk belongs to (counted from 1; a resumed run's next).
    """

    def __init__(self, learner: LearnsWhileCollecting, world: WorldModelParts, policy: TensorDictModuleBase,
                 seed: int, every: int, steps_per_epoch: int,
                 as_env_batch: Callable[[TensorDictBase], TensorDictBase], epoch: int) -> None:
        if not (isinstance(every, int) and 1 <= every <= steps_per_epoch and steps_per_epoch % every == 0):
            raise ValueError(f"imagination.refit_every={every!r} must divide each env's steps per epoch "
                             f"({steps_per_epoch})")
        self.learner, self.world, self.policy = learner, world, policy
        self.seed, self.every, self.steps_per_epoch = seed, every, steps_per_epoch
        self.as_env_batch = as_env_batch
        self.epoch = epoch
        self._pending: list[TensorDictBase] = []  # chunks not in the model's buffer yet
        self._steps = 0  # env steps of the epoch collected so far
        self._steps_in_buffer = 0  # of which the model's buffer holds
        self._refits, self._seconds = 0, 0.0  # this epoch's so far
        self._last_epoch = {"model/refits_within_epoch": 0.0, "model/refit_seconds": 0.0}

    def __call__(self, chunk: TensorDictBase) -> None:
        self.learner.update_chunk(chunk)
        self._pending.append(chunk)
        self._steps += chunk.shape[-1]
        if self._steps % self.every == 0 and self._steps < self.steps_per_epoch:
            self._refit()

    def _refit(self) -> None:
        started = time.perf_counter()
        world = self.world
        world.buffer.extend(self.as_env_batch(torch.cat(self._pending, dim=-1)), self.epoch)
        self._pending, self._steps_in_buffer = [], self._steps
        self._refits += 1
        contents = world.buffer.contents()
        world.trainer.fit(world.model, contents, reseed(self.seed, self.epoch, MODEL_FIT, self._refits))
        for rollout in world.imagination.epoch(self.epoch, contents, self.policy, part=self._refits):
            self.learner.update(rollout)
        self._seconds += time.perf_counter() - started

    def rest_of_epoch(self, batch: TensorDictBase) -> TensorDictBase:
        """The steps of the epoch's ``batch`` (``[envs, steps]``, assembled) that the model's buffer
        does not hold yet (those after the last refit), for the loop's fit after the epoch; the
        next chunk then begins the next epoch."""
        if batch.shape[-1] != self._steps:
            raise ValueError(f"the epoch's batch has {batch.shape[-1]} steps of each env, but its chunks brought "
                             f"{self._steps}: the refits see the epoch as its chunks come")
        rest = batch[..., self._steps_in_buffer:]
        self._last_epoch = {"model/refits_within_epoch": float(self._refits), "model/refit_seconds": self._seconds}
        self._pending, self._steps, self._steps_in_buffer = [], 0, 0
        self._refits, self._seconds = 0, 0.0
        self.epoch += 1
        return rest

    def metrics(self) -> dict[str, float]:
        """The refits within the epoch :meth:`rest_of_epoch` last ended, and their seconds (fits
        and imagination)."""
        return dict(self._last_epoch)
