"""TRPO as a :class:`~unipolicy_rl.learners.Learner`: GAE, one natural-gradient step and the critic fit per batch
(or, with the updater's ``clipped_step``, PPO: the same update with PPO's clipped epochs as its policy step).

The parts are :class:`~unipolicy_rl.objectives.TRPOLoss` and
:class:`~unipolicy_rl.objectives.TRPOUpdater`; this class adds what a run needs around them: the
observation normaliser and its statistics (refreshed between epochs, see
:mod:`unipolicy_rl.observation_statistics`), the stop when updates keep being skipped, and one
state to checkpoint.

The same class trains the flat policy and the token policies of ``robot=grammar``: what differs
is read off the policy (the raw keys it reads: its normaliser's input and the actor's other
inputs, such as the token and action masks) and told by ``statistics_keys`` (what the
statistics merge: the flat observation, or the tokens with their mask, so padding counts for
nothing).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import ObservationNorm

from unipolicy_rl.learners.base import StalledLearning, load_policy_state, policy_state, raw_observation_keys
from unipolicy_rl.objectives import TRPOUpdater
from unipolicy_rl.observation_statistics import ObservationStatistics, refresh_normalizer


class TRPOLearner:
    """One TRPO update per batch, on-policy (every batch is fresh data from the current policy).

    Args:
        actor, critic: the networks ``updater``'s loss was built on (read the normalised observation).
        updater: the TRPO update.
        normalizer: the policy's observation normaliser (its first module).
        policy: the collecting policy, ``normalizer`` then the actor.
        statistics: the observation statistics the normaliser is refreshed from.
        normalizer_refresh: ``preserve`` or ``jump`` (:func:`refresh_normalizer`).
        max_consecutive_skips: raise :class:`StalledLearning` after this many updates in a row
            skipped their policy step or critic fit.
        statistics_keys: the batch entries ``statistics.update`` takes, in order: the flat
            ``observation``, or the tokens and their mask for
            :class:`~unipolicy_rl.token_statistics.TokenObservationStatistics`.
    """

    def __init__(self, actor: TensorDictModuleBase, critic: TensorDictModuleBase, updater: TRPOUpdater,
                 normalizer: ObservationNorm, policy: TensorDictModuleBase,
                 statistics: ObservationStatistics, normalizer_refresh: str = "preserve",
                 max_consecutive_skips: int = 25, *,
                 statistics_keys: tuple[NestedKey, ...] = ("observation",)) -> None:
        self.actor, self.critic = actor, critic
        self.updater = updater
        self.loss = updater.loss_module
        self.normalizer = normalizer
        self.policy = policy
        self.statistics = statistics
        self.normalizer_refresh = normalizer_refresh
        self.max_consecutive_skips = max_consecutive_skips
        self.statistics_keys = tuple(statistics_keys)
        self.observation_keys = raw_observation_keys(normalizer, actor, critic)
        keys = self.loss.tensor_keys
        # (dict.fromkeys: an entry both observed and a distribution parameter, the action mask, once)
        self.batch_keys = tuple(dict.fromkeys((
            *self.observation_keys, keys.action, keys.sample_log_prob, *self.loss.actor_network.dist_params_keys,
            *(("next", key) for key in self.observation_keys), ("next", keys.reward), ("next", keys.done),
            ("next", keys.terminated))))

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self.normalizer(batch["next"])  # the critic's input at the next states, as the policy saw them
        metrics = self.updater.update(batch)
        if self.updater.consecutive_skips >= self.max_consecutive_skips:
            raise StalledLearning(f"stopping: {self.updater.consecutive_skips} updates in a row were skipped "
                                  f"({'; '.join(self.updater.skip_reasons)})")
        return metrics

    def real_surrogate(self, batch: TensorDictBase) -> torch.Tensor:
        """TRPO's surrogate of the current policy on ``batch``, a batch this learner has updated on,
        one term per sample: ``pi(a|s) / pi_k(a|s) * A`` with the collecting policy's
        log-probabilities and the (standardised) advantages of that update; the surrogate is their
        mean. What ``imagination.stopping.kind=real`` checks imagined updates against
        (:class:`~unipolicy_rl.collectors.RealCheck`, which pairs the terms of two checks).

        The observations are normalised afresh: the batch holds them as the collecting policy's
        normaliser saw them, before the epoch's refresh.

        Raises:
            KeyError: ``batch`` has no advantages (no update was taken on it), naming the key.
        """
        keys = self.loss.tensor_keys
        if keys.advantage not in batch.keys():
            raise KeyError(f"real_surrogate needs the batch's {keys.advantage!r} from a TRPO update on it: "
                           "call update(batch) first (imagination.train_on_real=true)")
        flat = batch.reshape(-1)
        probe = flat.select(*self.observation_keys, keys.action, keys.sample_log_prob).clone()
        with torch.no_grad():
            distribution = self.loss.policy_distribution(self.normalizer(probe))
            return self.loss.surrogate_terms(distribution, probe, self.loss.advantage(flat)).reshape(-1)

    def refresh_observation_normalizer(self, batch: TensorDictBase) -> dict[str, float]:
        """The trust region does not bound what a refresh does to the policy: its KL (on the
        batch's observations, with their masks) is logged."""
        self.updater.finish_critic_fit()  # (algo.critic_fit lagged or process: the refresh re-expresses the critic)
        probe = batch.select(*self.observation_keys).reshape(-1)
        with torch.no_grad():
            before = self.loss.policy_distribution(self.normalizer(probe.clone()))
            self.statistics.update(*(probe.get(key) for key in self.statistics_keys))
            refresh_normalizer(self.statistics, self.normalizer, (self.actor, self.critic), self.normalizer_refresh)
            after = self.loss.policy_distribution(self.normalizer(probe.clone()))
        self.updater.critic_changed()
        return {"train/refresh_kl": self.loss.mean_kl(before, after).item()}

    def policy_state(self) -> dict:
        return policy_state(self.actor, self.statistics)

    def start_from_policy(self, policy: dict) -> None:
        load_policy_state(self.actor, self.normalizer, policy)

    def state_dict(self) -> dict:
        self.updater.finish_critic_fit()
        critic_optimizer, critic_generator = self.updater.critic_optimizer_state()
        state = {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "observation_statistics": self.statistics.state_dict(),
            "critic_optimizer": critic_optimizer,
            "critic_generator": critic_generator,
        }
        if self.updater.clipped_step is not None:
            state["clipped_step"] = self.updater.clipped_step.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.statistics.load_state_dict(state["observation_statistics"])
        self.statistics.copy_to(self.normalizer)
        self.updater.finish_critic_fit()
        self.updater.load_critic_optimizer_state(state["critic_optimizer"], state["critic_generator"])
        self.updater.critic_changed()
        if self.updater.clipped_step is not None:
            if "clipped_step" not in state:
                raise KeyError("the checkpoint has no PPO policy optimizer ('clipped_step'): it was not saved by "
                               "algo=ppo; resume it with the algo it ran")
            self.updater.clipped_step.load_state_dict(state["clipped_step"])

    def close(self) -> None:
        self.updater.close()
