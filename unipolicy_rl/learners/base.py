"""The one interface the training loop asks of a policy learner: :class:`Learner`.

A learner owns the policy the collectors run and everything that changes it. The loop hands it
batches (real epochs, imagined branches) and, between epochs, the real observations its input
normaliser is refreshed from; it never looks inside. TRPO implements it on top of
:class:`~unipolicy_rl.objectives.TRPOLoss`; an off-policy learner implements it by keeping its own
replay buffer, adding each batch to it and taking as many gradient steps per real step as it is
configured to (``tests/test_learners.py`` runs the loop with such a learner).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey


@runtime_checkable
class Learner(Protocol):
    """A policy learner, as the training loop uses it.

    Attributes:
        policy: the collecting policy: raw ``observation`` in, ``action`` out (its observation
            normaliser inside). The real collectors and the imagined env run this module; the
            learner updates it in place.
        batch_keys: the keys :meth:`update` reads from a batch (a collector must provide them).
    """

    policy: TensorDictModuleBase
    batch_keys: tuple[NestedKey, ...]

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """Learns from ``batch`` (``[*envs, time]``, real or imagined); returns flat float metrics."""
        ...

    def refresh_observation_normalizer(self, batch: TensorDictBase) -> dict[str, float]:
        """Adds the observations of one epoch's real ``batch`` (the raw keys the policy reads) to
        the normaliser's statistics and moves the normaliser to them (it stays fixed within an
        epoch); returns metrics of what that did to the policy (e.g. the KL between the policy
        before and after)."""
        ...

    def policy_state(self) -> dict:
        """What :func:`~unipolicy_rl.checkpoint.load_policy` needs to rebuild the policy alone."""
        ...

    def start_from_policy(self, policy: dict) -> None:
        """Loads another run's :meth:`policy_state` (``init_policy``) into this new run's policy:
        the actor's weights and the normaliser; the rest of the learner stays as built."""
        ...

    def state_dict(self) -> dict:
        """Everything the learner continues from (weights, optimisers, statistics, RNG)."""
        ...

    def load_state_dict(self, state: dict) -> None:
        ...

    def close(self) -> None:
        """Ends what the learner runs beside the loop (``algo.critic_fit=process``'s process), so a
        run ends without waiting on an exit handler; idempotent, and a learner with nothing beside
        it does nothing."""
        ...


def policy_state(actor: TensorDictModuleBase, statistics) -> dict:
    """A learner's :meth:`Learner.policy_state`: the actor's weights and the normaliser's statistics."""
    return {"actor": actor.state_dict(), "observation_loc": statistics.loc, "observation_scale": statistics.scale}


def load_policy_state(actor: TensorDictModuleBase, normalizer: TensorDictModuleBase, policy: dict) -> None:
    """A learner's :meth:`Learner.start_from_policy`: ``policy`` (:func:`policy_state`'s layout)
    into ``actor`` and ``normalizer``. The learner's observation statistics stay empty: the first
    refresh moves the normaliser to this run's observations, re-expressing the actor (``preserve``)."""
    try:
        actor.load_state_dict(policy["actor"])
    except RuntimeError as error:  # another network: missing, unexpected or differently shaped weights
        raise ValueError(f"init_policy: its actor's weights do not load into this run's actor ({error})") from None
    normalizer.loc.copy_(policy["observation_loc"])
    normalizer.scale.copy_(policy["observation_scale"])


def raw_observation_keys(normalizer: TensorDictModuleBase, *networks: TensorDictModuleBase) -> tuple[NestedKey, ...]:
    """The raw keys a policy reads: the normaliser's input, then the networks' other inputs (masks,
    parents), in order and once each. A refresh's probe and a learner's ``batch_keys`` must carry
    all of them, or the networks meet a batch without their masks."""
    normalized = set(normalizer.out_keys)
    readers = [key for network in networks for key in network.in_keys if key not in normalized]
    return tuple(dict.fromkeys([*normalizer.in_keys, *readers]))


def observation_probe(observations: torch.Tensor) -> TensorDict:
    """``observations`` ``[..., size]`` as a flat batch of raw ``observation``: what a refresh
    compares the policy on, before and after."""
    flat = observations.reshape(-1, observations.shape[-1])
    return TensorDict({"observation": flat}, batch_size=[flat.shape[0]])


class StalledLearning(RuntimeError):
    """Raised by a learner whose updates keep being skipped: the run has stopped learning."""
