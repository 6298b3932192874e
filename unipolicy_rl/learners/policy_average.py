"""An exponential moving average of the policy's weights as the policy that acts (``algo.policy_average``).

A model-based run's policy moves after every imagined update, and a step the model was wrong
about reaches the robot at once: the policy walks, then one design falls back for a few
evaluations (the league's records, docs/league/runs). Averaging the weights over the last few
epochs (Polyak averaging, as ``torch.optim.swa_utils.AveragedModel`` and the target networks of
off-policy RL keep it) smooths those moves out of the policy that acts, while the learner goes
on training its own weights.

:class:`AveragedLearner` wraps an on-policy learner: its :attr:`~AveragedLearner.policy`, the one
the real collectors run, the periodic evaluation measures and the checkpoints save (``policy``
of checkpoint.pt and best.pt, which ``load_policy`` reads), is the average's; the imagined
rollouts train the learner's own weights (:attr:`~AveragedLearner.learning_policy`, what
:func:`learning_policy` returns), so TRPO stays on-policy on its imagined data. After each real
epoch's updates the loop takes one step, ``average <- decay * average + (1 - decay) * weights``
(:meth:`~AveragedLearner.average_step`). The average starts at the learner's initial weights (so
it is a policy from the first epoch on, with no bias to correct).

The observation normaliser is the learner's, shared: both actors read the same normalised
observation. A ``preserve`` refresh re-expresses the average's first layer exactly as it does the
learner's (:func:`~unipolicy_rl.observation_statistics.reexpress_networks`), so the refresh leaves
the acting policy's output unchanged too, and the two sets of weights are always in the same
coordinates when averaged; with ``jump`` both move with the normaliser.

Every floating-point entry of the actor's state (weights, the Gaussian's log-std, any running
statistics) is averaged; any other entry (a counter) is copied. The average is part of the
learner's state (``state_dict()["policy_average"]``), so a resumed run continues it bit for bit.
With ``imagination.train_on_real`` the real batch comes from the average, and TRPO's update on it
weighs it by ``pi / pi_average``, as for any batch of another policy.
"""

from __future__ import annotations

import copy
import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from unipolicy_rl.learners.base import Learner, load_policy_state, policy_state
from unipolicy_rl.metric_columns import POLICY_AVERAGE_DISTANCE
from unipolicy_rl.observation_statistics import reexpress_networks
from unipolicy_rl.policy import make_collecting_policy

STATE_KEY = "policy_average"  # the average's weights in the learner's state_dict
DISTANCE = POLICY_AVERAGE_DISTANCE  # (metrics.csv's column, while averaging)


def check_decay(decay) -> None:
    """``decay`` is off (None or 0) or a weight in (0, 1) the average keeps at each step."""
    if decay is None:
        return
    if isinstance(decay, bool) or not isinstance(decay, (int, float)) or not (math.isfinite(decay) and 0 <= decay < 1):
        raise ValueError(f"algo.policy_average.decay must lie in [0, 1) (0 or null: off), got {decay!r}")


def averaging(decay) -> bool:
    """Whether ``algo.policy_average.decay`` turns the average on."""
    check_decay(decay)
    return bool(decay)


def average_step(average: torch.nn.Module, weights: torch.nn.Module, decay: float) -> float:
    """``average <- decay * average + (1 - decay) * weights``, entry by entry, in place (collectors that
    share the average's memory see it); returns the relative distance left between them."""
    gap, norm = 0.0, 0.0
    with torch.no_grad():
        source = weights.state_dict()
        for name, value in average.state_dict().items():
            new = source[name]
            if value.is_floating_point():
                value.lerp_(new, 1.0 - decay)
                gap += float((value.double() - new.double()).square().sum())
                norm += float(new.double().square().sum())
            else:
                value.copy_(new)
    return math.sqrt(gap / norm) if norm > 0 else 0.0


class AveragedLearner:
    """``learner`` (a :class:`~unipolicy_rl.learners.TRPOLearner`: an ``actor``, a ``normalizer``,
    ``statistics``) whose acting policy is an exponential moving average of its actor's weights.

    It is a :class:`~unipolicy_rl.learners.Learner`; anything else (``updater``, ``real_surrogate``)
    is the wrapped learner's.

    Args:
        learner: the learner that trains.
        decay: the weight the average keeps at each step, in (0, 1).
    """

    def __init__(self, learner: Learner, decay: float) -> None:
        if not averaging(decay):
            raise ValueError(f"AveragedLearner needs a decay in (0, 1), got {decay!r}")
        for name in ("actor", "normalizer", "statistics", "normalizer_refresh"):
            if not hasattr(learner, name):
                raise ValueError(f"algo.policy_average averages an on-policy learner's actor; "
                                 f"{type(learner).__name__} has no {name!r}")
        self.learner, self.decay = learner, float(decay)
        self.learning_policy = learner.policy
        self.average_actor = copy.deepcopy(learner.actor)
        self.policy = make_collecting_policy(learner.normalizer, self.average_actor)
        self.batch_keys = learner.batch_keys

    def __getattr__(self, name: str):
        if name == "learner":  # (not yet set: during unpickling or a failed __init__)
            raise AttributeError(name)
        return getattr(self.learner, name)

    def average_step(self) -> dict[str, float]:
        """One step of the average towards the learner's current weights (once per real epoch,
        after its updates)."""
        return {DISTANCE: average_step(self.average_actor, self.learner.actor, self.decay)}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        return self.learner.update(batch)

    def refresh_observation_normalizer(self, batch: TensorDictBase) -> dict[str, float]:
        normalizer = self.learner.normalizer
        old_loc, old_scale = normalizer.loc.detach().clone(), normalizer.scale.detach().clone()
        metrics = self.learner.refresh_observation_normalizer(batch)
        if self.learner.normalizer_refresh == "preserve":
            reexpress_networks((self.average_actor,), old_loc, old_scale, normalizer.loc.detach(),
                               normalizer.scale.detach())
        return metrics

    def policy_state(self) -> dict:
        """The average's actor with the shared normaliser's statistics: the policy a checkpoint hands over."""
        return policy_state(self.average_actor, self.learner.statistics)

    def start_from_policy(self, policy: dict) -> None:
        self.learner.start_from_policy(policy)
        load_policy_state(self.average_actor, self.learner.normalizer, policy)

    def state_dict(self) -> dict:
        return {**self.learner.state_dict(), STATE_KEY: copy.deepcopy(self.average_actor.state_dict())}

    def load_state_dict(self, state: dict) -> None:
        """The learner's state and the average; a checkpoint of a run that did not average starts the
        average at the learner's weights."""
        self.learner.load_state_dict(state)
        self.average_actor.load_state_dict(state.get(STATE_KEY, self.learner.actor.state_dict()))

    def close(self) -> None:
        self.learner.close()


def learning_policy(learner: Learner) -> TensorDictModuleBase:
    """The policy ``learner`` trains (what imagined rollouts run): an :class:`AveragedLearner`'s own
    weights, else the policy that acts."""
    return learner.learning_policy if isinstance(learner, AveragedLearner) else learner.policy


def end_of_epoch(learner: Learner) -> dict[str, float]:
    """After a real epoch's updates: an :class:`AveragedLearner`'s averaging step and its metrics
    (nothing for any other learner)."""
    return learner.average_step() if isinstance(learner, AveragedLearner) else {}
