"""Imagined batches for policy updates: where branches start, how long they run, when to stop.

The thesis' Algorithm 5 (MOE-TRPO), done as model-based RL has learned to do it since (MBPO,
ME-TRPO): after each model fit, the policy trains on imagined trajectories that start from real
states, either short branches of ``horizon`` steps from any buffered state (MBPO; the horizon
grows on a schedule) or whole episodes from real start states (the thesis). A branch's last
step is truncated, never terminated, so the value estimator bootstraps from the critic there.
Optionally a branch ends earlier, at the step where the world model's members disagree about
the next state past a threshold (MACURA's cut; :mod:`unipolicy_rl.world_models.disagreement`),
truncated in the same way; TorchRL's rollout then restarts that row from a fresh real state.
How many updates follow a fit is the stopping rule's call: a fixed number (the thesis),
ME-TRPO's check of the policy's return under every member, or a check on the epoch's real batch
that keeps only the updates the robot's own data say helped (:class:`RealCheck`).

:class:`Imagination` owns all of that (the imagined env, the start states, the horizon, the
rule); the training loop asks it for one epoch's batches, ``imagination.epoch(...)``, and
iterates.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.collectors.real import IMAGINED, label, truncate_last_step
from unipolicy_rl.collectors.replay import COLLECTED_IN
from unipolicy_rl.envs.limits import EXPLOSION_LIMIT
from unipolicy_rl.objectives.adaptive_kl import AdaptiveKL
from unipolicy_rl.seeding import IMAGINATION, epoch_seed
from unipolicy_rl.world_models.disagreement import (
    DISAGREEMENT,
    DISAGREEMENT_CUT,
    DISAGREEMENT_PENALTY,
    DisagreementCut,
    DisagreementPenalty,
    change_scale,
    check_members_disagree,
    check_penalty_weight,
    check_threshold,
)
from unipolicy_rl.world_models.dynamics import Dynamics
from unipolicy_rl.world_models.imagined import (
    ImaginedEnv,
    Reward,
    Termination,
    context_keys,
    make_world_model,
    member_returns,
)
from unipolicy_rl.world_models.trainer import EPISODE_START

ROLLOUTS = ("branch", "episode")
STOPPING_RULES = ("fixed", "metrpo", "real")


@dataclass(frozen=True)
class HorizonSchedule:
    """Imagined branch length: ``start`` up to epoch ``first_epoch``, then linear to ``end`` at
    ``last_epoch`` (MBPO grows it from 1 to 25 as the model improves)."""

    start: int = 10
    end: int = 25
    first_epoch: int = 5
    last_epoch: int = 30

    def __post_init__(self) -> None:
        for name in ("start", "end"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"horizon.{name} must be an integer >= 1, got {value!r}")
        if not self.first_epoch <= self.last_epoch:
            raise ValueError(f"horizon.first_epoch ({self.first_epoch!r}) must not exceed "
                             f"horizon.last_epoch ({self.last_epoch!r})")

    def __call__(self, epoch: int) -> int:
        if epoch <= self.first_epoch or self.first_epoch == self.last_epoch:
            return self.start if epoch <= self.first_epoch else self.end
        progress = min(1.0, (epoch - self.first_epoch) / (self.last_epoch - self.first_epoch))
        return int(round(self.start + progress * (self.end - self.start)))


@dataclass(frozen=True)
class StoppingRule:
    """How many imagined policy updates follow each model fit.

    ``fixed``: always ``max_updates`` (the thesis). ``metrpo`` (ME-TRPO): every
    ``check_every`` updates, the policy's imagined return is measured under every voting member
    from the same start states; the epoch's updates stop when fewer than
    ``min_improving_fraction`` of them still see it improve, or at ``max_updates``. ``real``:
    every ``check_every`` updates (and after the last), TRPO's surrogate on the epoch's real
    batch; the updates stop at the first check where it did not rise, and the policy goes back to
    the last check where it did (:class:`RealCheck`; needs the real batch's TRPO update,
    ``train_on_real``). With ``tolerance`` > 0 a check also passes where the surrogate fell below
    its best by at most that many standard errors of the fall (the batch's samples paired).

    Who votes is the model's ``voting_members``: every member of an ensemble, elites or not, as
    ME-TRPO checks every model it trained. Elites are ranked on one-step validation error, a
    ranking that shifts from fit to fit; the rule asks whether an improvement holds across all
    the models the data allow, and a member the data fit slightly worse is one of them. A
    model whose members are design cells has no voters (:func:`check_stopping_rule`).
    """

    kind: str = "metrpo"
    max_updates: int = 20
    check_every: int = 5
    min_improving_fraction: float = 0.7
    check_starts: int = 50
    check_horizon: int = 20
    tolerance: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in STOPPING_RULES:
            raise ValueError(f"stopping.kind must be one of {STOPPING_RULES}, got {self.kind!r}")
        for name in ("max_updates", "check_every", "check_starts", "check_horizon"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"stopping.{name} must be an integer >= 1, got {value!r}")
        if not 0 < self.min_improving_fraction <= 1:
            # 0 would never stop early: the fraction improving is never below 0.
            raise ValueError(f"stopping.min_improving_fraction must lie in (0, 1], got {self.min_improving_fraction!r}")
        if not (isinstance(self.tolerance, (int, float)) and 0 <= self.tolerance < math.inf):
            raise ValueError("stopping.tolerance must be a finite number >= 0 (standard errors), "
                             f"got {self.tolerance!r}")
        if self.tolerance and self.kind != "real":
            raise ValueError(f"stopping.tolerance={self.tolerance!r} applies to stopping.kind=real only, "
                             f"not {self.kind!r}")

    def keeps_going(self, baseline: torch.Tensor, current: torch.Tensor) -> tuple[bool, float]:
        """After a check: whether updates go on, and the fraction of voting members whose return
        under the policy rose above ``baseline`` (each member's return at the last check)."""
        improving = float((current > baseline).float().mean())
        return improving >= self.min_improving_fraction, improving


@dataclass(frozen=True)
class ImaginationSettings:
    """Imagined data per policy update.

    Args:
        steps_per_batch: imagined steps in one batch (trajectories x horizon).
        rollout: ``branch`` (short branches from any real state, horizon on a schedule) or
            ``episode`` (whole episodes from real start states, as the thesis did).
        horizon: branch length schedule (``episode`` uses the episode length).
        member_per_step: draw the predicting member anew at every step instead of once per trajectory.
        start_epochs: draw imagined trajectories' start states from the real transitions of the
            latest this many epochs only (None: the whole buffer). TRPO is on-policy: starts near
            the current policy's own states make its imagined advantages about states it visits.
        deterministic: imagine with each member's mean prediction, without its noise (the members'
            spread is then the only randomness; for a model whose noise is independent per output).
        train_on_real: also take a policy update on each real batch.
        disagreement_cut: end a branch at the step where the members' disagreement about the next
            state passes this (in units of a typical real step's change; see
            :mod:`~unipolicy_rl.world_models.disagreement`), truncated; None: branches run their
            horizon (ending early only on a model fault).
        disagreement_penalty: take this times the members' disagreement about each imagined
            step's next state (the cut's units) off that step's reward, as MOPO lowers the reward
            where the model is unsure; None: the reward as the env or the model gives it.
        buffer_capacity: real transitions kept (FIFO).
        fit_every: real epochs from one model fit to the next (1: after every epoch). In between,
            the policy still trains on imagined branches from the newest real states, under the
            model of the latest fit: one more epoch of data changes a model fitted on tens of
            epochs little, and the fit is the largest cost of a model-based epoch (mbrl-lib's
            ``freq_train_model``; MBPO refits every 250 real steps).
        background_fit: fit the model on a second thread while the policy trains on the previous
            fit's model (one epoch older), the new weights taking over when the epoch's updates
            are done (:class:`~unipolicy_rl.world_models.PendingFit`). Pays on a machine with a
            core to spare: the epoch then takes about the longer of the fit and the updates, not
            their sum. The first fit, with no model before it, runs before the updates.
        refit_every: an off-policy learner's model refreshes while the epoch is collected (MBPO:
            every 250 real steps): every this many env steps (of each env) the real data so far
            join the model's buffer, the model is refitted and one imagined batch from the
            current policy goes to the learner (:class:`~unipolicy_rl.collectors.refits.RefitsWithinEpoch`;
            needs ``algo.update_every``); the fit after the epoch stays. None: that fit only.
        stopping: how many updates follow each model fit.
        adaptive_kl: the imagined updates' KL bound, shrunk as the model's fresh error rises
            (:class:`~unipolicy_rl.objectives.adaptive_kl.AdaptiveKL`; off by default).
    """

    steps_per_batch: int = 5000
    rollout: str = "branch"
    horizon: HorizonSchedule = HorizonSchedule()
    member_per_step: bool = False
    start_epochs: int | None = None
    deterministic: bool = False
    train_on_real: bool = False
    disagreement_cut: float | None = None
    disagreement_penalty: float | None = None
    buffer_capacity: int = 200_000
    fit_every: int = 1
    background_fit: bool = False
    refit_every: int | None = None
    stopping: StoppingRule = StoppingRule()
    adaptive_kl: AdaptiveKL = AdaptiveKL()

    def __post_init__(self) -> None:
        if self.rollout not in ROLLOUTS:
            raise ValueError(f"rollout must be one of {ROLLOUTS}, got {self.rollout!r}")
        for name in ("steps_per_batch", "buffer_capacity", "fit_every"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("start_epochs", "refit_every"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        if self.disagreement_cut is not None:
            check_threshold(self.disagreement_cut)
        if self.disagreement_penalty is not None:
            check_penalty_weight(self.disagreement_penalty)
        if not isinstance(self.background_fit, bool):
            raise ValueError(f"background_fit must be true or false, got {self.background_fit!r}")
        if self.stopping.kind == "real" and not self.train_on_real:
            raise ValueError("stopping.kind=real checks the imagined updates against the epoch's real batch, with the "
                             "advantages of the TRPO update on it: set train_on_real=true")

    def fits_after(self, epoch: int) -> bool:
        """Whether the world model is fitted after real epoch ``epoch`` (counted from 1): the first
        epoch and every ``fit_every``-th after it, so a run's fits depend on its epoch alone (a
        resumed run fits where the straight one did)."""
        return (epoch - 1) % self.fit_every == 0


def check_stopping_rule(stopping: StoppingRule, model: Dynamics) -> None:
    """Refuses ME-TRPO's rule for a model whose members cannot vote (one per design cell), by name."""
    if stopping.kind == "metrpo" and model.voting_members is None:
        raise ValueError(f"imagination.stopping.kind=metrpo compares a policy's return under every member, but "
                         f"{type(model).__name__}'s members model different designs (one per cell), not "
                         f"alternatives of one robot: use imagination.stopping.kind=fixed with this world model")


class Imagination:
    """Imagined batches from a fitted world model, one epoch at a time.

    Args:
        model: the world model's dynamics (fitted by the loop before each epoch's imagination).
        reference_env: an env whose specs the imagined env copies (it is not stepped).
        reward: the walker's ``RewardWeights``, a known reward (a TensorDict module of the real
            env's keys) or ``"learned"`` (the model's reward head): see
            :func:`~unipolicy_rl.world_models.make_world_model`.
        settings: imagined data per update, and the stopping rule.
        seed: the run's seed (each epoch's imagination restarts from its own seed).
        episode_length: real episode length (the ``episode`` rollout's horizon).
        termination: None (branches end only at the horizon, a fault or the cut, truncated), a
            known termination function, or ``"learned"``.
        blowup_limit: a predicted state with a magnitude at or past it is a fault (truncated).

    Raises:
        ValueError: ``stopping.kind=metrpo`` with a model whose members cannot vote (one per
            design cell), or ``disagreement_cut`` with a model whose members cannot disagree (one
            per design cell, or a single one), naming the model.
    """

    def __init__(self, model: Dynamics, reference_env: EnvBase, reward: Reward, settings: ImaginationSettings,
                 seed: int, episode_length: int, termination: Termination = None,
                 blowup_limit: float = EXPLOSION_LIMIT) -> None:
        check_stopping_rule(settings.stopping, model)
        for name in ("disagreement_cut", "disagreement_penalty"):
            if getattr(settings, name) is not None:
                check_members_disagree(model, f"imagination.{name}")
        stopping = settings.stopping
        self.model = model
        self.reference_env = reference_env
        self.reward, self.termination, self.blowup_limit = reward, termination, blowup_limit
        make_world_model(model, reward, termination=termination, blowup_limit=blowup_limit)  # refuses bad ones now
        self.settings = settings
        self.stopping = stopping
        self.seed = seed
        self.episode_length = episode_length

    @property
    def train_on_real(self) -> bool:
        """Whether the policy also takes an update on each real batch."""
        return self.settings.train_on_real

    def horizon(self, epoch: int) -> int:
        return self.episode_length if self.settings.rollout == "episode" else self.settings.horizon(epoch)

    def epoch(self, epoch: int, transitions: TensorDictBase, policy: TensorDictModuleBase,
              real_surrogate: Callable[[], torch.Tensor] | None = None, part: int | None = None) -> ImaginedEpoch:
        """The imagined batches of ``epoch`` (iterate them; each is one policy update's data),
        branching from ``transitions`` (the replay buffer's contents), rolled out by ``policy``;
        ``part``: the refit within the epoch they follow (``refit_every``; None: the fit after it).

        ``real_surrogate`` (``stopping.kind=real`` only, and needed there): the current policy's
        TRPO surrogate on the epoch's real batch, one term per sample (the surrogate is their
        mean), e.g. ``partial(learner.real_surrogate, batch)``.
        """
        if self.stopping.kind == "real" and real_surrogate is None:
            raise ValueError("stopping.kind=real needs real_surrogate: the policy's TRPO surrogate on the "
                             "epoch's real batch (TRPOLearner.real_surrogate)")
        torch.manual_seed(epoch_seed(self.seed, epoch, IMAGINATION, part))
        horizon = self.horizon(epoch)
        starts = self._start_sampler(transitions, epoch)
        cut, penalty = self._disagreement_uses(transitions)
        env = ImaginedEnv(
            make_world_model(self.model, self.reward, self.settings.member_per_step, self.settings.deterministic, cut,
                             self.termination, self.blowup_limit, penalty),
            self.reference_env, starts, max(1, self.settings.steps_per_batch // horizon),
        )
        real_check = (None if self.stopping.kind != "real" else
                      RealCheck(policy, real_surrogate, self.stopping.tolerance))
        return ImaginedEpoch(self, env, policy, horizon, starts(self.stopping.check_starts), real_check)

    def _disagreement_uses(self, transitions: TensorDictBase
                           ) -> tuple[DisagreementCut | None, DisagreementPenalty | None]:
        """The cut and the penalty this epoch (None where off), in one unit: each output's spread of
        real one-step changes in the buffer, as of now."""
        settings = self.settings
        if settings.disagreement_cut is None and settings.disagreement_penalty is None:
            return None, None
        scale = change_scale(transitions, self.model.layout.robot_size)
        return (None if settings.disagreement_cut is None else DisagreementCut(settings.disagreement_cut, scale),
                None if settings.disagreement_penalty is None else
                DisagreementPenalty(settings.disagreement_penalty, scale))

    def _start_sampler(self, data: TensorDictBase, epoch: int):
        pool = data if self.settings.rollout == "branch" else data[data.get(EPISODE_START)]
        window = self.settings.start_epochs
        if window is not None and COLLECTED_IN in pool.keys():  # (a buffer from before the key: all of it)
            pool = pool[pool.get(COLLECTED_IN) > epoch - window]
        pool = pool.select("state", *context_keys(self.model), *self.model.layout.build_keys)

        def sample(n: int) -> TensorDictBase:
            return pool[torch.randint(pool.batch_size[0], (n,))]

        return sample

    def member_returns(self, policy: TensorDictModuleBase, starts: TensorDictBase) -> torch.Tensor:
        """The deterministic policy's mean imagined return from ``starts`` under each voting member."""
        world_model = make_world_model(self.model, self.reward, deterministic=True, termination=self.termination,
                                       blowup_limit=self.blowup_limit)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return member_returns(world_model, self.reference_env, policy, starts, self.stopping.check_horizon)


class RealCheck:
    """The ``real`` stopping rule: imagined updates kept only while the robot's own data agree.

    A model's members cannot show a bias they share (the PCE's bootstrap members share its own:
    docs/results.md, "Polynomial chaos"), and then ME-TRPO's vote lets the policy climb the
    model's optimum rather than the robot's. The epoch's real batch can: TRPO's surrogate on it,
    ``mean(pi(a|s) / pi_k(a|s) * A_k)`` with the collecting policy ``pi_k``'s actions and
    advantages, estimates the real return's change to first order. The imagined updates never
    saw that batch, so a rise of the surrogate between two checks is an unbiased sign that those
    updates helped on the robot (the real update's own fit to the batch's noise does not enter
    the difference). At the first check where it did not rise, the policy's weights go back to
    the last check where it kept them, and the epoch's updates stop.

    That sign is noisy: on 1,000 real samples the change a few updates make is often within the
    estimate's noise, and a good model's updates are then refused as often as a biased one's
    (docs/results.md, "twelfth day": the ensemble with this rule). ``tolerance`` > 0 also keeps the updates where the
    surrogate fell below its best by at most ``tolerance`` standard errors of that fall, the
    samples paired (the same batch under both policies): only a fall the batch can tell from
    noise stops the epoch.

    Args:
        policy: the collecting policy the updates change (its weights are what is restored).
        surrogate: the current policy's surrogate on the epoch's real batch, one term per sample.
        tolerance: standard errors of its fall below the best check the surrogate may lose and
            the updates still be kept (0: it must rise).
    """

    def __init__(self, policy: TensorDictModuleBase, surrogate: Callable[[], torch.Tensor],
                 tolerance: float = 0.0) -> None:
        self.policy, self.surrogate, self.tolerance = policy, surrogate, tolerance
        self.best_terms = surrogate()
        self.start = self.best = self.kept_value = float(self.best_terms.mean())
        self.kept = self._weights()
        self.checked_at = 0  # updates taken when last checked
        self.kept_updates = 0  # updates in the policy the rule last kept

    def improved(self, updates: int) -> bool:
        """After ``updates`` updates: whether the surrogate rose above its best so far (or, with a
        tolerance, fell below it within the noise); if not, the policy is restored to the last
        check that kept it."""
        self.checked_at = updates
        terms = self.surrogate()
        current = float(terms.mean())
        if current > self.best:
            self.best, self.best_terms = current, terms
        elif not self._within_noise(terms, current):
            self.policy.load_state_dict(self.kept)
            return False
        self.kept, self.kept_updates, self.kept_value = self._weights(), updates, current
        return True

    def _within_noise(self, terms: torch.Tensor, current: float) -> bool:
        """Whether ``current`` is at most ``tolerance`` standard errors of the paired change below the best."""
        if not self.tolerance or terms.numel() < 2:
            return False
        change = terms - self.best_terms
        return current - self.best >= -self.tolerance * float(change.std()) / math.sqrt(change.numel())

    def finish(self, updates: int) -> None:
        """The last updates, if no check has seen them yet (the rule ran to ``max_updates``)."""
        if updates > self.checked_at:
            self.improved(updates)

    def metrics(self, prefix: str) -> dict[str, float]:
        return {f"{prefix}kept_updates": float(self.kept_updates),
                f"{prefix}real_surrogate_gain": self.kept_value - self.start}

    def _weights(self) -> dict[str, torch.Tensor]:
        return {name: value.detach().clone() for name, value in self.policy.state_dict().items()}


class ImaginedEpoch:
    """One epoch's imagined batches: iterating rolls the policy out once per batch (the loop
    updates the policy in between) until the stopping rule says stop; :meth:`metrics` then tells
    how many updates ran and, under ME-TRPO's rule, the fraction of members still improving
    (under the ``real`` rule: how many updates it kept, and their gain on the real batch)."""

    def __init__(self, imagination: Imagination, env: ImaginedEnv, policy: TensorDictModuleBase,
                 horizon: int, check_starts: TensorDictBase, real_check: RealCheck | None = None) -> None:
        self.imagination, self.env, self.policy, self.horizon = imagination, env, policy, horizon
        self.check_starts = check_starts
        self.real_check = real_check
        self.updates = 0
        self.improving: float | None = None
        self.rollout_seconds = 0.0  # what the last batch took to imagine (its check included)

    def __iter__(self) -> Iterator[TensorDictBase]:
        stopping = self.imagination.stopping
        checks = self._checks()
        while True:
            started = time.perf_counter()
            if not (self.updates < stopping.max_updates and next(checks)):
                break
            with torch.no_grad():
                rollout = self.env.rollout(self.horizon, self.policy, break_when_any_done=False)
            truncate_last_step(rollout)
            self.rollout_seconds = time.perf_counter() - started
            self.updates += 1
            yield label(rollout, IMAGINED)
        if self.real_check is not None:
            self.real_check.finish(self.updates)

    def _checks(self) -> Iterator[bool]:
        """Before every update, whether updates may go on (the stopping rule)."""
        stopping = self.imagination.stopping
        if stopping.kind == "fixed":
            while True:
                yield True
        if stopping.kind == "real":
            while True:
                yield True
                if self.updates % stopping.check_every == 0 and not self.real_check.improved(self.updates):
                    yield False
                    return
        baseline = self.imagination.member_returns(self.policy, self.check_starts)
        while True:
            yield True
            if self.updates % stopping.check_every == 0:
                current = self.imagination.member_returns(self.policy, self.check_starts)
                going, self.improving = stopping.keeps_going(baseline, current)
                if not going:
                    yield False
                    return
                baseline = current

    def metrics(self, prefix: str = "model/") -> dict[str, float]:
        out = {f"{prefix}policy_updates": float(self.updates)}
        if self.improving is not None:
            out[f"{prefix}improving_members"] = self.improving
        if self.real_check is not None:
            out.update(self.real_check.metrics(prefix))
        return out


def imagined_metrics(rollout: TensorDictBase) -> dict[str, float]:
    """What one imagined batch held: reward, branch return, model faults, horizon, steps, and the
    mean branch length (a fault or the disagreement cut ends a branch before the horizon; a row
    of the batch then holds more than one). With the cut or the penalty: the mean disagreement
    over the steps (those where every member's prediction was finite); with the cut, the share of
    branches it ended; with the penalty, the mean reward it took off a step (the reward figures
    are after it)."""
    reward = rollout.get(("next", "reward"))
    # Every branch ends with done (its last step is truncated by the time metrics are taken).
    branches = max(1, int(rollout.get(("next", "done")).sum()))
    metrics = {
        "imagined/reward_per_step": reward.mean().item(),
        "imagined/branch_return": reward.sum(dim=(-2, -1)).mean().item(),
        "imagined/model_faults": rollout.get(("next", "physics_fault")).sum().item(),
        "imagined/horizon": float(reward.shape[-2]),
        "imagined/steps": float(reward.numel()),
        "imagined/branch_length": reward.numel() / branches,
    }
    keys = rollout.keys(include_nested=True)
    if ("next", DISAGREEMENT) in keys:
        disagreement = rollout.get(("next", DISAGREEMENT))
        finite = disagreement[torch.isfinite(disagreement)]
        metrics["imagined/disagreement"] = finite.mean().item() if finite.numel() else float("nan")
    if ("next", DISAGREEMENT_CUT) in keys:
        metrics["imagined/cut_share"] = int(rollout.get(("next", DISAGREEMENT_CUT)).sum()) / branches
    if ("next", DISAGREEMENT_PENALTY) in keys:
        metrics["imagined/disagreement_penalty"] = rollout.get(("next", DISAGREEMENT_PENALTY)).mean().item()
    return metrics


__all__ = [
    "HorizonSchedule",
    "check_stopping_rule",
    "Imagination",
    "ImaginationSettings",
    "ImaginedEpoch",
    "RealCheck",
    "StoppingRule",
    "imagined_metrics",
]
