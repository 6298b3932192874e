"""``env=gym``: a gymnasium task (``env.id``) as the training loop runs it, through TorchRL's ``GymEnv``.

What the walker's config says through ``robot`` and ``design``, a gym task says through
``env`` (``conf/env/gym.yaml``): its id, the real env steps of one epoch, the reward and
termination a world model uses (known where exact, else learned), how many episodes an
evaluation averages, and the return levels a run is measured by.

The policy acts in ``[-1, 1]`` on every action, whatever the task's bounds: TorchRL's
``ActionScaling`` maps that box onto the task's own (Pendulum's torque in ``[-2, 2]``) and a clip
keeps a Gaussian policy's sample inside it, as the walker clips its own. So TRPO, SAC's
tanh-squashed actor and the world model see the same action box on every env, and the env's
own bounds are read from its spec, never assumed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gymnasium
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import (
    ActionScaling,
    ClipTransform,
    Compose,
    DoubleToFloat,
    GymEnv,
    InitTracker,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl import metric_columns as columns
from unipolicy_rl.envs.gym_functions import known_reward, known_termination

WALKER, GYM = "walker", "gym"
ENV_KINDS = (WALKER, GYM)
KNOWN, LEARNED, AUTO, NONE = "known", "learned", "auto", "none"

# Return levels the docs and the league report measure a gym task by (env.levels overrides):
# Pendulum's -200 (swung up and held), InvertedPendulum's 1,000 (balanced the whole episode),
# and Hopper's three of the MBPO comparison.
KNOWN_LEVELS = {"Pendulum": (-200.0,), "InvertedPendulum": (1000.0,), "Hopper": (1000.0, 2500.0, 3000.0),
                "Walker2d": (1000.0, 2500.0, 3000.0), "HalfCheetah": (1000.0, 3000.0, 5000.0)}


def make_gym_env(num_envs: int = 1, *, env_id: str) -> TransformedEnv:
    """One gymnasium task ``env_id`` as TorchRL's ``GymEnv``: acting in ``[-1, 1]`` (module
    docstring), observing in float32 (MuJoCo observes in float64), marking where each episode
    begins (``is_init``: the replay buffer reads episode starts from it) and counting its steps
    (``step_count``: an episode that reached the time limit ended). ``num_envs`` is the
    collector's count of robots; a gym task runs one env."""
    if num_envs != 1:
        raise ValueError(f"env=gym runs one env per collector, got {num_envs} (set workers=1, episodes_per_epoch=1)")
    env = GymEnv(env_id)
    check_bounded_continuous_action(env, env_id)
    return TransformedEnv(env, Compose(DoubleToFloat(), InitTracker(), StepCounter(), ActionScaling(),
                                       ClipTransform(in_keys_inv=["action"], out_keys_inv=["action"],
                                                     low=-1.0, high=1.0)))


def check_bounded_continuous_action(env, env_id: str) -> None:
    """Refuses, naming the task, an action the unit box cannot stand for: a discrete or unbounded one."""
    spec = env.action_spec
    if not spec.dtype.is_floating_point:
        raise ValueError(f"env.id={env_id!r} has a discrete action ({spec.dtype}); env=gym trains continuous actions")
    low, high = spec.space.low, spec.space.high
    if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
        raise ValueError(f"env.id={env_id!r} has an unbounded action ({low.tolist()} to {high.tolist()}); env=gym "
                         "needs a bounded continuous action it can scale to [-1, 1]")


@dataclass(frozen=True)
class GymTask:
    """``env`` of an ``env=gym`` config, checked (``conf/env/gym.yaml`` says what each field means)."""

    id: str
    frames_per_epoch: int
    reward: str
    termination: str
    evaluation_episodes: int
    levels: tuple[float, ...]

    def __post_init__(self) -> None:
        try:
            gymnasium.spec(self.id)
        except gymnasium.error.Error as error:
            raise ValueError(f"env.id={self.id!r} is not a registered gymnasium env ({error})") from None
        for key, value in (("frames_per_epoch", self.frames_per_epoch),
                           ("evaluation_episodes", self.evaluation_episodes)):
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"env.{key} must be a positive integer, got {value!r}")
        if self.reward not in (AUTO, KNOWN, LEARNED):
            raise ValueError(f"env.reward must be one of {(AUTO, KNOWN, LEARNED)}, got {self.reward!r}")
        if self.termination not in (AUTO, KNOWN, LEARNED, NONE):
            raise ValueError(f"env.termination must be one of {(AUTO, KNOWN, LEARNED, NONE)}, got {self.termination!r}")
        if self.reward == KNOWN and known_reward(self.id) is None:
            raise ValueError(f"env.reward=known: no exact reward of {self.id!r} is known here "
                             f"(unipolicy_rl.envs.gym_functions.REWARDS); use env.reward=learned")
        if self.termination == KNOWN and known_termination(self.id) is None:
            raise ValueError(f"env.termination=known: no termination of {self.id!r} is known here "
                             f"(unipolicy_rl.envs.gym_functions.TERMINATIONS); use learned or none")
        if not self.levels or any(not math.isfinite(level) for level in self.levels):
            raise ValueError(f"env.levels must be finite return thresholds, got {list(self.levels)!r}")

    @property
    def episode_length(self) -> int:
        """The task's time limit (gymnasium's ``max_episode_steps``)."""
        steps = gymnasium.spec(self.id).max_episode_steps
        if steps is None:
            raise ValueError(f"env.id={self.id!r} has no time limit (max_episode_steps); env=gym needs one")
        return int(steps)

    @property
    def reward_source(self) -> str:
        """``known`` or ``learned``: ``auto`` is the known reward where there is one."""
        if self.reward != AUTO:
            return self.reward
        return KNOWN if known_reward(self.id) is not None else LEARNED

    @property
    def termination_source(self) -> str:
        """``known``, ``learned`` or ``none``: ``auto`` is the known termination where there is one, else
        none for a task that never ends early (Pendulum), else learned."""
        if self.termination != AUTO:
            return self.termination
        if known_termination(self.id) is not None:
            return KNOWN
        return NONE if self.id.split("-")[0] in NEVER_TERMINATES else LEARNED

    def learned_heads(self) -> list[str]:
        """What the world model learns beside the next state (``GaussianEnsemble(learn=...)``)."""
        return [name for name, source in (("reward", self.reward_source), ("terminated", self.termination_source))
                if source == LEARNED]


# Tasks that only ever end at their time limit.
NEVER_TERMINATES = {"Pendulum", "HalfCheetah", "Swimmer", "Reacher", "MountainCarContinuous"}





class ActionInEnvUnits(TensorDictModuleBase):
    """A known reward written in the task's own action units (Pendulum's torque), read on the
    policy's ``[-1, 1]`` action: the action is clipped and mapped back as the env maps it
    (``ActionScaling``), then the reward is computed on a shallow copy."""

    def __init__(self, reward: TensorDictModuleBase, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.reward = reward
        self.in_keys, self.out_keys = list(reward.in_keys), list(reward.out_keys)
        self.register_buffer("loc", (high + low) / 2)
        self.register_buffer("scale", (high - low) / 2)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        view = tensordict.copy()
        view.set("action", self.loc + self.scale * tensordict.get("action").clamp(-1.0, 1.0))
        out = self.reward(view)
        for key in self.out_keys:
            tensordict.set(key, out.get(key))
        return tensordict


def world_model_reward(task: GymTask):
    """The reward an imagined step gets: the task's known reward (in its action units), or ``learned``."""
    if task.reward_source == LEARNED:
        return LEARNED
    base = GymEnv(task.id)
    low, high = base.action_spec.space.low, base.action_spec.space.high
    base.close()
    return ActionInEnvUnits(known_reward(task.id), low, high)


def world_model_termination(task: GymTask):
    """The termination an imagined step gets: known, ``learned``, or None (the task never ends early)."""
    source = task.termination_source
    return known_termination(task.id) if source == KNOWN else (LEARNED if source == LEARNED else None)


def gym_episode_metrics(batch: TensorDictBase, episode_length: int) -> dict[str, float]:
    """The real episodes that ended in the epoch: their mean return (NaN when none ended), and the
    mean reward per step. An episode the epoch's end cut (the collector marks the last step
    truncated) is not counted; one that ended there by itself is (terminated, or at the time limit)."""
    done = batch["next", "done"].squeeze(-1).clone()
    done[..., -1] = (batch["next", "terminated"][..., -1, 0]
                     | (batch["next", "step_count"][..., -1, 0] >= episode_length))
    returns = batch["next", "episode_reward"].squeeze(-1)[done]
    return {columns.REWARD: returns.mean().item() if returns.numel() else math.nan,
            columns.REWARD_PER_STEP: batch["next", "reward"].mean().item()}


def evaluate_returns(policy: TensorDictModuleBase, env_id: str, episodes: int, seed: int,
                     max_steps: int) -> list[float]:
    """The deterministic policy's return in each of ``episodes`` real episodes of ``env_id``
    (the env seeded once with ``seed``; each episode resets from the next draw)."""
    env = make_gym_env(env_id=env_id)
    env.set_seed(seed)
    returns = []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            rollout = env.rollout(max_steps, policy, break_when_any_done=True)
            returns.append(rollout["next", "reward"].sum().item())
    env.close()
    return returns
