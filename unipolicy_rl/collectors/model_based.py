"""The model-based collector: real episodes, a model fit, then imagined batches, repeated.

The thesis' Algorithm 5 (MOE-TRPO), done as model-based RL has learned to do it since
(MBPO, ME-TRPO): every epoch collects real episodes with the current policy into a FIFO
replay buffer, fits the world model on the buffer, then yields imagined batches for policy
updates until the stopping rule says stop. Imagined trajectories start from real states:
short branches of ``horizon`` steps from any buffered state (MBPO; the horizon grows on a
schedule), or whole episodes from real start states (the thesis). A branch's last step is
truncated, never terminated, so the value estimator bootstraps from the critic there.

Iterating yields TensorDicts like TorchRL's collectors, each labelled ``real`` or
``imagined`` (:data:`~unipolicy_rl.collectors.real.DATA_SOURCE`). The trainer updates the
policy between ``next`` calls; the collector sees the update because it rolls the same
policy module out in this process.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.collectors.real import IMAGINED, RealEpochCollector, epoch_seed, label, truncate_last_step
from unipolicy_rl.envs.reward import RewardWeights
from unipolicy_rl.world_models.ensemble import DynamicsModel
from unipolicy_rl.world_models.imagined import ImaginedWalkerEnv, make_world_model, member_returns
from unipolicy_rl.world_models.trainer import FitReport, ModelTrainer

MODEL_FIT, IMAGINATION = 1, 2  # phases of an epoch, each reseeded (see epoch_seed)
COLLECTED_IN = "collected_in"  # the real epoch a buffered transition came from (1 = the first)
ROLLOUTS = ("branch", "episode")
STOPPING_RULES = ("fixed", "metrpo")


@dataclass(frozen=True)
class HorizonSchedule:
    """Imagined branch length: ``start`` up to epoch ``first_epoch``, then linear to ``end`` at
    ``last_epoch`` (MBPO grows it from 1 to 25 as the model improves)."""

    start: int = 10
    end: int = 10
    first_epoch: int = 1
    last_epoch: int = 1

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
    ``check_every`` updates, the policy's imagined return is measured under every member
    from the same start states; the epoch's updates stop when fewer than
    ``min_improving_fraction`` of the members still see it improve, or at ``max_updates``.
    """

    kind: str = "fixed"
    max_updates: int = 10
    check_every: int = 5
    min_improving_fraction: float = 0.7
    check_starts: int = 50
    check_horizon: int = 20

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
        buffer_capacity: real transitions kept (FIFO).
    """

    steps_per_batch: int = 5000
    rollout: str = "branch"
    horizon: HorizonSchedule = HorizonSchedule()
    member_per_step: bool = False
    start_epochs: int | None = None
    deterministic: bool = False
    train_on_real: bool = False
    buffer_capacity: int = 200_000

    def __post_init__(self) -> None:
        if self.rollout not in ROLLOUTS:
            raise ValueError(f"rollout must be one of {ROLLOUTS}, got {self.rollout!r}")
        for name in ("steps_per_batch", "buffer_capacity"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.start_epochs is not None and not (isinstance(self.start_epochs, int) and self.start_epochs >= 1):
            raise ValueError(f"start_epochs must be a positive integer or None, got {self.start_epochs!r}")


def transitions(batch: TensorDictBase, state_of, memory_of=None) -> TensorDict:
    """One row per real step of ``batch`` (``[robots, steps]``) for the model to fit:
    state, action, design, next state, and whether the state began an episode. Steps the
    physics faulted on are left out (their next state is a repeat, not physics).

    ``state_of`` maps the env's ``full`` state to the model's; ``memory_of`` (a model's
    :meth:`~unipolicy_rl.world_models.DynamicsModel.memory_of`) gives the memory columns to
    append to the states before and after each step, or None for a model without memory."""
    keep = ~batch.get(("next", "physics_fault")).squeeze(-1)
    start = torch.zeros(batch.batch_size, dtype=torch.bool)
    start[..., 0] = True  # every epoch starts every robot from a reset
    state, next_state = state_of(batch.get("state")), state_of(batch.get(("next", "state")))
    memory = None if memory_of is None else memory_of(batch)
    if memory is not None:
        state, next_state = torch.cat([state, memory[0]], -1), torch.cat([next_state, memory[1]], -1)
    rows = TensorDict(
        {
            "state": state,
            "action": batch.get("action").clamp(-1.0, 1.0),
            "design": batch.get("design"),
            "next_state": next_state,
            "episode_start": start,
        },
        batch_size=batch.batch_size,
    )
    return rows[keep]


class ModelBasedCollector:
    """Alternates real batches and imagined batches (see the module docstring).

    Args:
        real: the real-data collector (one epoch of episodes per batch).
        model: the dynamics model; fitted in place every epoch, warm-started.
        trainer: fits the model.
        policy: the collecting policy (raw observation -> action), shared with the trainer.
        reference_env: an env whose specs the imagined env copies.
        reward_weights: the real env's reward weights.
        imagination: imagined data settings.
        stopping: updates per epoch.
        seed: the run's seed.
        episode_length: real episode length (the ``episode`` rollout's horizon).
    """

    def __init__(self, real: RealEpochCollector, model: DynamicsModel, trainer: ModelTrainer,
                 policy: TensorDictModuleBase, reference_env: EnvBase, reward_weights: RewardWeights,
                 imagination: ImaginationSettings, stopping: StoppingRule, seed: int, episode_length: int) -> None:
        self.real = real
        self.model = model
        self.trainer = trainer
        self.policy = policy
        self.reference_env = reference_env
        self.reward_weights = reward_weights
        self.imagination = imagination
        self.stopping = stopping
        self.seed = seed
        self.episode_length = episode_length
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(imagination.buffer_capacity), batch_size=1)
        self.model_fitted_for = 0  # the last epoch whose model phase has run
        self.imagined_updates = 0
        self._metrics: dict[str, float] = {}
        self.last_fit: FitReport | None = None

    @property
    def trains_policy_on_real(self) -> bool:
        return self.imagination.train_on_real

    @property
    def real_env_steps(self) -> int:
        return self.real.real_env_steps

    @property
    def epoch(self) -> int:
        """Real epochs collected so far."""
        return self.real.epoch

    def __iter__(self) -> Iterator[TensorDictBase]:
        if self.real.epoch > self.model_fitted_for:  # resumed right after a real batch
            yield from self._model_phase()
        for batch in self.real:
            rows = transitions(batch, self.model.layout.from_full, self.model.memory_of)
            if len(self.buffer) == 0 or COLLECTED_IN in self.buffer[:1].keys():  # (not into an older run's buffer)
                rows.set(COLLECTED_IN, torch.full(rows.batch_size, self.real.epoch, dtype=torch.long))
            self.buffer.extend(rows)
            yield batch
            yield from self._model_phase()

    # -- one epoch's model phase ----------------------------------------------------------
    def _model_phase(self) -> Iterator[TensorDictBase]:
        epoch = self.real.epoch
        # ---- Model training
        torch.manual_seed(epoch_seed(self.seed, epoch, MODEL_FIT))
        data = self.buffer[: len(self.buffer)]
        self.last_fit = self.trainer.fit(self.model, data, torch.Generator().manual_seed(epoch_seed(self.seed, epoch,
                                                                                                     MODEL_FIT)))
        self._metrics.update(self.last_fit.as_metrics())
        # ---- Policy training on imagined data
        torch.manual_seed(epoch_seed(self.seed, epoch, IMAGINATION))
        horizon = self.episode_length if self.imagination.rollout == "episode" else self.imagination.horizon(epoch)
        trajectories = max(1, self.imagination.steps_per_batch // horizon)
        starts = self._start_sampler(data)
        env = ImaginedWalkerEnv(
            make_world_model(self.model, self.reward_weights, self.imagination.member_per_step,
                             self.imagination.deterministic),
            self.reference_env, starts, trajectories,
        )
        check = self._improvement_check(starts(self.stopping.check_starts))
        updates = 0
        while updates < self.stopping.max_updates and next(check):
            with torch.no_grad():
                rollout = env.rollout(horizon, self.policy, break_when_any_done=False)
            truncate_last_step(rollout)
            updates += 1
            self.imagined_updates += 1
            self._metrics.update(imagined_metrics(rollout, horizon))
            yield label(rollout, IMAGINED)
        self._metrics["model/policy_updates"] = float(updates)
        self.model_fitted_for = epoch

    def _start_sampler(self, data: TensorDictBase):
        pool = data if self.imagination.rollout == "branch" else data[data.get("episode_start")]
        window = self.imagination.start_epochs
        if window is not None and COLLECTED_IN in pool.keys():  # (a buffer from before the key: all of it)
            pool = pool[pool.get(COLLECTED_IN) > self.real.epoch - window]
        pool = pool.select("state", "design")

        def sample(n: int) -> TensorDictBase:
            return pool[torch.randint(pool.batch_size[0], (n,))]

        return sample

    def _improvement_check(self, starts: TensorDictBase) -> Iterator[bool]:
        """Yields before every update whether updates may go on (the stopping rule)."""
        if self.stopping.kind == "fixed":
            while True:
                yield True
        world_model = make_world_model(self.model, self.reward_weights, deterministic=True)

        def returns() -> torch.Tensor:
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                return member_returns(world_model, self.reference_env, self.policy, starts,
                                      self.stopping.check_horizon)

        baseline = returns()
        done = 0
        while True:
            yield True
            done += 1
            if done % self.stopping.check_every == 0:
                current = returns()
                improving = float((current > baseline).float().mean())
                self._metrics["model/improving_members"] = improving
                if improving < self.stopping.min_improving_fraction:
                    yield False
                    return
                baseline = current

    # -- the collector interface --------------------------------------------------------
    def metrics(self) -> dict[str, float]:
        """Collector-side figures since the last call (model fit, stopping rule, real steps)."""
        out, self._metrics = {**self._metrics, **self.real.metrics()}, {}
        return out

    def update_policy_weights_(self) -> None:
        self.real.update_policy_weights_()

    def shutdown(self) -> None:
        self.real.shutdown()

    def state_dict(self) -> dict:
        return {
            "real": self.real.state_dict(),
            "model": self.model.state_dict(),
            "buffer": self.buffer.state_dict(),
            "model_fitted_for": self.model_fitted_for,
            "imagined_updates": self.imagined_updates,
        }

    def load_state_dict(self, state: dict) -> None:
        self.real.load_state_dict(state["real"])
        self.model.load_state_dict(state["model"])
        self.buffer.load_state_dict(state["buffer"])
        self.model_fitted_for = int(state["model_fitted_for"])
        self.imagined_updates = int(state["imagined_updates"])


def imagined_metrics(rollout: TensorDictBase, horizon: int) -> dict[str, float]:
    reward = rollout.get(("next", "reward"))
    return {
        "imagined/reward_per_step": reward.mean().item(),
        "imagined/branch_return": reward.sum(dim=(-2, -1)).mean().item(),
        "imagined/model_faults": rollout.get(("next", "physics_fault")).sum().item(),
        "imagined/horizon": float(horizon),
        "imagined/steps": float(reward.numel()),
    }


__all__ = [
    "HorizonSchedule",
    "ImaginationSettings",
    "ModelBasedCollector",
    "StoppingRule",
    "imagined_metrics",
    "transitions",
]
