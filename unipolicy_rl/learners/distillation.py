"""One policy for many robots, taught by a specialist per robot: DAgger as a :class:`~unipolicy_rl.learners.Learner`.

A universal policy trained by TRPO over many morphologies learns each robot far more slowly than a
specialist trained on that robot alone (docs/grammar.md); what the specialists learned is already
paid for. Distillation (Rusu et al. 2016; Ross et al. 2011's DAgger; the behaviour distillation of
Furuta et al. 2023 across morphologies) moves it into one network: the student runs on the real
robots of its training set, every step it visits is labelled with the deterministic action of that
robot's specialist, and the student's mean action is regressed on every label so far. Labelling the
student's own states (not only the teachers' trajectories) is DAgger's point: the student learns
what to do where its own mistakes take it.

The student is a token policy of :mod:`unipolicy_rl.policy` (the same network and observation
normaliser TRPO trains), so a distilled checkpoint evaluates, loads and goes on training as any
other. The teachers are specialist checkpoints (``robot.specialist``), matched to the student's
training morphologies by derivation; each must run on the env the student runs on (the same
padding, physics, reward and token settings), which :class:`SpecialistTeachers` checks at start-up.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.transforms import ObservationNorm
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.collectors.buffer_state import compact_state, load_compact_state
from unipolicy_rl.envs.tokens import ACTION_MASK, MORPHOLOGY, TOKEN_MASK, TOKENS
from unipolicy_rl.learners.base import load_policy_state, policy_state, raw_observation_keys
from unipolicy_rl.observation_statistics import REFRESH_MODES, ObservationStatistics, refresh_normalizer

TEACHER_ACTION = "teacher_action"
# Env settings a teacher must share with the student (every MorphologyWalkerEnv argument but the
# morphologies drawn and how, and the episodes' length, which changes no step): the same tokens,
# padding, designs, physics and reward.
SHARED_ENV_SETTINGS = ("max_links", "design", "physics", "reward_weights", "driven_joints", "design_in_tokens",
                       "token_layout", "clock_frequency")


def differing_env_settings(ours: dict, theirs: dict) -> list[str]:
    """The :data:`SHARED_ENV_SETTINGS` in which two ``MorphologyWalkerEnv`` argument sets differ:
    a policy's tokens mean the same on both only where there are none."""
    return [key for key in SHARED_ENV_SETTINGS if ours.get(key) != theirs.get(key)]


@dataclass(frozen=True)
class DistillationSettings:
    """``conf/algo/distill.yaml``.

    Args:
        teachers: specialist checkpoints (``checkpoint.pt`` or ``best.pt`` of runs with
            ``robot.specialist``), one for each morphology the student trains on, in any order.
        learning_rate: Adam's step size for the student's mean.
        batch_size: labelled steps per gradient step.
        updates_per_epoch: gradient steps after each real epoch's labels are added.
        buffer_capacity: labelled steps kept (FIFO; DAgger's aggregate, cut to the latest epochs).
        normalizer_refresh: ``preserve`` (the student's first layers re-expressed so a refresh
            leaves its actions as they were) or ``jump``.
    """

    teachers: tuple[str, ...]
    learning_rate: float = 1e-3
    batch_size: int = 256
    updates_per_epoch: int = 50
    buffer_capacity: int = 20_000
    normalizer_refresh: str = "preserve"

    def __post_init__(self) -> None:
        if not self.teachers:
            raise ValueError("algo.teachers is empty: give a specialist checkpoint for every training morphology "
                             "(algo.teachers=[runs/specialists/train0/checkpoint.pt,...])")
        for name in ("batch_size", "updates_per_epoch", "buffer_capacity"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"algo.{name} must be an integer >= 1, got {value!r}")
        if not (isinstance(self.learning_rate, (int, float)) and self.learning_rate > 0):
            raise ValueError(f"algo.learning_rate must be positive, got {self.learning_rate!r}")
        if self.normalizer_refresh not in REFRESH_MODES:
            raise ValueError(f"algo.normalizer_refresh must be one of {REFRESH_MODES}, got {self.normalizer_refresh!r}")


class SpecialistTeachers:
    """The deterministic actions of each robot's specialist, for a batch of the student's env.

    Args:
        student_env_kwargs: the student's ``MorphologyWalkerEnv`` arguments (its ``morphologies``
            are the set whose indices the env writes as ``morphology``).
        teachers: checkpoint paths; each is loaded, and must be a specialist
            (``robot.specialist``) whose robot is one of the student's morphologies, on the
            student's env settings (:data:`SHARED_ENV_SETTINGS`).

    Raises:
        ValueError: naming the checkpoint and what is wrong: not a specialist, a robot the student
            does not train on, two teachers for one robot, another env setting; or naming the
            student's morphologies left without a teacher.
    """

    def __init__(self, student_env_kwargs: dict, teachers: Sequence[str | Path]) -> None:
        from unipolicy_rl.checkpoint import load_policy  # (checkpoint imports the policy stack)

        morphologies = student_env_kwargs["morphologies"]
        index_of = {morphology: index for index, morphology in enumerate(morphologies)}
        self.policies: dict[int, TensorDictModuleBase] = {}
        self.paths: dict[int, str] = {}
        for path in map(str, teachers):
            if not Path(path).is_file():  # (checked here, not in the settings: a plan names teachers yet to be trained)
                raise ValueError(f"algo.teachers: no checkpoint at {path!r}")
            loaded = load_policy(path)
            specialist = loaded.specialist
            robots = loaded.env_kwargs.get("morphologies", ())
            if specialist is None or len(robots) != 1:
                raise ValueError(f"algo.teachers: {path} is not a specialist's checkpoint (a robot=grammar run with "
                                 f"robot.specialist set, trained on one robot)")
            index = index_of.get(robots[0])
            if index is None:
                raise ValueError(f"algo.teachers: {path}'s robot is none of the {len(morphologies)} morphologies the "
                                 f"student trains on ({robots[0]})")
            if index in self.paths:
                raise ValueError(f"algo.teachers: {path} and {self.paths[index]} both teach morphology {index}")
            differing = differing_env_settings(loaded.env_kwargs, student_env_kwargs)
            if differing:
                key = differing[0]
                raise ValueError(f"algo.teachers: {path} ran with another {key} ({loaded.env_kwargs.get(key)!r}) "
                                 f"than the student's env ({student_env_kwargs.get(key)!r})")
            self.policies[index], self.paths[index] = loaded.policy, path
        missing = [index for index in range(len(morphologies)) if index not in self.policies]
        if missing:
            raise ValueError(f"algo.teachers: no specialist for morphologies {missing} of the {len(morphologies)} "
                             f"the student trains on (robot.training_morphologies); give one checkpoint for each")

    @torch.no_grad()
    @set_exploration_type(ExplorationType.DETERMINISTIC)
    def actions(self, batch: TensorDictBase) -> torch.Tensor:
        """``[*batch, L]``: each step's action of its robot's specialist (its Gaussian's mean,
        clipped to the env's [-1, 1] as the env clips it; 0 on padded slots)."""
        flat = batch.reshape(-1)
        morphology = flat[MORPHOLOGY].reshape(-1)
        labels = torch.zeros(flat[ACTION_MASK].shape)
        for index in morphology.unique().tolist():
            rows = morphology == index
            if index not in self.policies:
                raise KeyError(f"the batch holds morphology {index}, which no teacher teaches")
            taught = self.policies[index](flat[rows].exclude("action", "loc", "scale", "sample_log_prob").clone())
            labels[rows] = taught["loc"].clamp(-1.0, 1.0)
        return torch.where(flat[ACTION_MASK], labels, torch.zeros(())).reshape(batch.shape + labels.shape[-1:])


class DistillationLearner:
    """DAgger: after each real epoch of the student's own steps, their specialists' actions are
    added to a buffer of labelled steps and the student's mean is regressed on minibatches of it
    (the squared error over real joints). The student's standard deviation is left as it is: it is
    the exploration a later TRPO run starts from, and here the noise that shows the teachers
    states just off the student's path (as DART does).

    Args:
        settings: :class:`DistillationSettings`.
        actor: the student's Gaussian token policy (reads the normalised tokens).
        normalizer, policy, statistics: the observation normaliser, the collecting policy
            (``normalizer`` then ``actor``) and the statistics the normaliser is refreshed from.
        teachers: :class:`SpecialistTeachers` of the student's training morphologies.
        generator: draws the minibatches (its state is checkpointed: a resumed run draws the
            same ones; torch's global randomness after a collection is the collector's).
        statistics_keys: the batch entries ``statistics.update`` takes (the tokens and their mask).
    """

    def __init__(self, settings: DistillationSettings, actor: TensorDictModuleBase, normalizer: ObservationNorm,
                 policy: TensorDictModuleBase, statistics: ObservationStatistics, teachers: SpecialistTeachers,
                 generator: torch.Generator, *,
                 statistics_keys: tuple[NestedKey, ...] = (TOKENS, TOKEN_MASK)) -> None:
        self.settings = settings
        self.actor, self.normalizer, self.policy, self.statistics = actor, normalizer, policy, statistics
        self.teachers = teachers
        self.statistics_keys = tuple(statistics_keys)
        self.observation_keys = raw_observation_keys(normalizer, actor)
        self.batch_keys = tuple(dict.fromkeys((*self.observation_keys, MORPHOLOGY)))
        self.optimizer = torch.optim.Adam(actor.parameters(), lr=settings.learning_rate)
        self.generator = generator
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(settings.buffer_capacity), generator=generator)
        self.gradient_steps = 0

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        flat = batch.reshape(-1).select(*self.batch_keys).clone()
        flat[TEACHER_ACTION] = self.teachers.actions(flat)
        with torch.no_grad():  # how far the student acting now is from its teachers, before this epoch's steps
            gap = self._squared_error(flat).item()
        self.buffer.extend(flat)
        losses = [self._gradient_step() for _ in range(self.settings.updates_per_epoch)]
        return {"distill/teacher_gap": gap, "distill/loss": sum(losses) / len(losses),
                "distill/gradient_steps": float(self.gradient_steps), "distill/buffer_size": float(len(self.buffer))}

    def _squared_error(self, labelled: TensorDictBase) -> torch.Tensor:
        """Mean over real joints of (student's mean - teacher's action)^2."""
        mean = self.actor.get_dist(self.normalizer(labelled.clone())).mean
        mask = labelled[ACTION_MASK]
        error = torch.where(mask, mean - labelled[TEACHER_ACTION], torch.zeros(()))
        return error.square().sum() / mask.sum().clamp_min(1)

    def _gradient_step(self) -> float:
        loss = self._squared_error(self.buffer.sample(self.settings.batch_size))
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.gradient_steps += 1
        return loss.item()

    def refresh_observation_normalizer(self, batch: TensorDictBase) -> dict[str, float]:
        """Refreshed as TRPO's: the stored steps keep their raw tokens and are normalised when
        drawn, so every label is read with the current statistics."""
        probe = batch.select(*self.observation_keys).reshape(-1)
        with torch.no_grad():
            before = self.actor.get_dist(self.normalizer(probe.clone())).mean
            self.statistics.update(*(probe.get(key) for key in self.statistics_keys))
            refresh_normalizer(self.statistics, self.normalizer, (self.actor,), self.settings.normalizer_refresh)
            after = self.actor.get_dist(self.normalizer(probe.clone())).mean
        mask = probe[ACTION_MASK]
        moved = torch.where(mask, after - before, torch.zeros(())).abs().amax().item()
        return {"distill/refresh_max_mean_change": moved}

    def policy_state(self) -> dict:
        return policy_state(self.actor, self.statistics)

    def start_from_policy(self, policy: dict) -> None:
        load_policy_state(self.actor, self.normalizer, policy)

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "observation_statistics": self.statistics.state_dict(),
                "optimizer": self.optimizer.state_dict(), "buffer": compact_state(self.buffer),
                "gradient_steps": self.gradient_steps, "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.statistics.load_state_dict(state["observation_statistics"])
        self.statistics.copy_to(self.normalizer)
        self.optimizer.load_state_dict(state["optimizer"])
        load_compact_state(self.buffer, state["buffer"])
        self.gradient_steps = state["gradient_steps"]
        self.generator.set_state(state["generator"])

    def close(self) -> None:
        """Nothing runs beside the loop."""
