"""What a world model's state vector holds, and the views of it a model and a policy need.

:class:`Layout` is what every world model reads of its state (sizes, the model's input
features, the policy's observation, the keys, how an action enters the model); two layouts
implement it for flat states:

* :class:`FlatLayout`, the general one, read off any TorchRL env with a flat continuous
  observation and a bounded continuous action (:meth:`FlatLayout.from_env`): the state is the
  observation itself, the features are the state, the policy observes the state, there is no
  design and no build;
* :class:`StateLayout`, one configuration of it for the walker: the state is one of the env's
  observation layouts without the design, per body (the base first) position xyz then velocity
  xyz, then, in the ``full`` layout, the actuated joints' angles and rates. Its input features
  are translation invariant: the base's x, y are dropped and every other body's x, y are taken
  relative to the base, so a gait learned at x = 0 holds at x = 3 m (MBPO/ME-TRPO remove
  positions from the input for the same reason); the policy's observation is the columns of
  the env's ``observation`` layout within the state, with the design (l, rho) appended when the
  env appends it, so the policy sees exactly what the real env would show it.

A model whose prediction needs more than the env's state (the thesis' ME-PCE needs the step
within the episode and the last actions) carries it as ``memory_size`` columns after that
state; the model fills them (``Dynamics.memory_of``), the env only passes them on.

The keys (``state_key``, ``observation_key``, ``build_keys``, ``design_size``) say where the
replay buffer reads the state, what the imagined env writes for the policy and which context it
carries; the link-token layout of a grammar robot
(:class:`~unipolicy_rl.world_models.token_layout.TokenLayout`) is a :class:`Layout` with other keys.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import torch
from torchrl.envs import EnvBase

VALUES_PER_BODY = 6  # position xyz, velocity xyz


class Layout:
    """What every world model reads of its state; the defaults are a flat state's.

    Subclasses give ``robot_size`` (the env's own state, before a model's memory) and
    ``memory_size``, and override the views where the state holds more than numbers in a row.
    """

    # The env key the state is read from, the key the policy reads (:meth:`observation`), and the
    # keys of the robot's build that an imagined step carries unchanged from its start state.
    state_key: str = "observation"
    observation_key: str = "observation"
    build_keys: tuple[str, ...] = ()
    # Numbers of the design (or any context the env reports beside the state, under ``design``)
    # that every model takes as an input: 0 for a plain env.
    design_size: int = 0
    # The action's bounds (the env's action spec), per action; None: [-1, 1] (the walker's).
    action_low: tuple[float, ...] | None = None
    action_high: tuple[float, ...] | None = None
    robot_size: int
    memory_size: int

    @property
    def size(self) -> int:
        """The env's state and the model's memory after it."""
        return self.robot_size + self.memory_size

    @property
    def feature_size(self) -> int:
        return self.robot_size

    @property
    def observation_shape(self) -> tuple[int, ...]:
        """The shape of one env's :meth:`observation`."""
        return (self.robot_size,)

    @property
    def velocity_columns(self) -> list[int]:
        """The columns a model may hold within the range seen in the data (the PCE's clamp on
        predicted velocities): of a flat state, every one (none is a position that may wander)."""
        return list(range(self.robot_size))

    def from_full(self, state: torch.Tensor) -> torch.Tensor:
        """The model's state (without memory) of what the env reports under ``state_key``."""
        return state

    def features(self, state: torch.Tensor) -> torch.Tensor:
        """The model's input features of ``state`` (its memory left out)."""
        return state[..., :self.robot_size]

    def observation(self, state: torch.Tensor, design: torch.Tensor | None = None) -> torch.Tensor:
        """What the policy reads of ``state``: the env's state itself (a copy, so the policy's
        observation and the model's state never alias within a step)."""
        return state[..., :self.robot_size].clone()

    def applied_action(self, action: torch.Tensor) -> torch.Tensor:
        """The action the env applies: the policy's, clipped to the action spec's bounds.

        A bounded env clips what it is given (gymnasium's classic-control and MuJoCo envs, the
        walker's joint targets), and the policies here are Gaussians that leave the clipping to
        the env (:func:`~unipolicy_rl.networks.make_actor`): the model must see what the env did.
        """
        if self.action_low is None:
            return action.clamp(-1.0, 1.0)
        low, high = self._bounds(action)
        return torch.maximum(torch.minimum(action, high), low)

    def scaled_action(self, action: torch.Tensor) -> torch.Tensor:
        """The applied action mapped to [-1, 1] by the spec's bounds: every model's action input."""
        applied = self.applied_action(action)
        if self.action_low is None:
            return applied
        low, high = self._bounds(action)
        return (applied - low) / (high - low) * 2 - 1

    def _bounds(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.tensor(self.action_low, dtype=action.dtype, device=action.device),
                torch.tensor(self.action_high, dtype=action.dtype, device=action.device))


def check_action_bounds(low: Sequence[float], high: Sequence[float]) -> None:
    """Refuses bounds a model cannot scale by: unequal lengths, infinite, or not low < high."""
    if low is None or high is None or len(low) != len(high) or not low:
        raise ValueError(f"action bounds must be one low and one high per action, got {low!r} and {high!r}")
    for index, (lo, hi) in enumerate(zip(low, high, strict=True)):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"action {index} has bounds [{lo!r}, {hi!r}]: a world model needs a bounded action "
                             f"(finite, low < high) to scale it from its spec")


@dataclass(frozen=True)
class FlatLayout(Layout):
    """The state of a plain env: its flat observation of ``robot_size`` numbers, as it is.

    Args:
        robot_size: numbers in the env's observation (the model's state).
        action_low, action_high: the action spec's bounds, per action.
        observation_key: the env's observation key: the model's state and the policy's input.
        memory_size: columns a model appends to the state (set by the model, e.g. a PC-NARX's lags).
    """

    robot_size: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    observation_key: str = "observation"
    memory_size: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.robot_size, bool) or not (isinstance(self.robot_size, int) and self.robot_size >= 1):
            raise ValueError(f"robot_size must be a positive integer (the observation's numbers), "
                             f"got {self.robot_size!r}")
        check_action_bounds(self.action_low, self.action_high)

    @property
    def state_key(self) -> str:  # the env reports its state as its observation
        return self.observation_key

    @classmethod
    def from_env(cls, env: EnvBase, observation_key: str = "observation") -> FlatLayout:
        """The layout of ``env`` (any TorchRL ``EnvBase``): its flat observation ``observation_key``
        is the state, its bounded action spec scales the action. Refuses, by name, an observation
        that is not one flat vector and an action spec that is not bounded and continuous."""
        one = (0,) * len(env.batch_size)
        if observation_key not in env.observation_spec.keys(include_nested=True):
            raise ValueError(f"the env has no observation {observation_key!r}; it has "
                             f"{sorted(map(str, env.observation_spec.keys(include_nested=True)))}")
        observation = env.observation_spec[observation_key][one]
        if len(observation.shape) != 1 or not observation.dtype.is_floating_point:
            raise ValueError(f"observation {observation_key!r} must be one flat float vector, got shape "
                             f"{tuple(observation.shape)} and dtype {observation.dtype}")
        action = env.action_spec[one]
        space = getattr(action, "space", None)
        if len(action.shape) != 1 or not action.dtype.is_floating_point or not hasattr(space, "low"):
            raise ValueError(f"the action must be one bounded float vector (a Bounded spec), got "
                             f"{type(action).__name__} of shape {tuple(action.shape)} and dtype {action.dtype}")
        low = tuple(float(v) for v in space.low.reshape(-1))
        high = tuple(float(v) for v in space.high.reshape(-1))
        return cls(int(observation.shape[0]), low, high, observation_key)


@dataclass(frozen=True)
class StateLayout(Layout):
    """Indices into a state of ``size`` numbers: ``num_bodies`` bodies then ``num_joint_values``.

    ``state_columns`` place the state within the env's ``full`` layout (the ``state`` key of a
    ``BatchedWalkerEnv(full_state=True)``); ``observation_columns`` place the policy's
    observation within the state.
    """

    # The env key the robot's state is read from (a ``BatchedWalkerEnv(full_state=True)``'s);
    # the policy reads ``observation``; one robot, one build (no build keys); every model takes
    # the design (l, rho); the action is the joints' targets in [-1, 1] (no bounds given).
    state_key: ClassVar[str] = "state"
    design_size: ClassVar[int] = 2

    num_bodies: int
    num_joint_values: int
    state_columns: tuple[int, ...]
    observation_columns: tuple[int, ...]
    append_design: bool = False
    memory_size: int = 0

    @classmethod
    def for_env(cls, robot, observation: str, append_design: bool, model_state: str) -> StateLayout:
        """The layout of a model that predicts ``model_state`` for a policy that observes ``observation``.

        ``model_state`` may be richer than ``observation`` (``full`` for a ``thesis`` policy),
        never poorer: the policy's inputs must be derivable from what the model predicts.
        ``robot``: the walker's ``RobotSettings``.
        """
        from unipolicy_rl.envs.simulation import OBSERVATIONS, observation_columns  # the walker's (PyBullet)

        for name, value in (("observation", observation), ("model_state", model_state)):
            if value not in OBSERVATIONS:
                raise ValueError(f"{name} must be one of {OBSERVATIONS}, got {value!r}")
        if model_state == "thesis" and observation == "full":
            raise ValueError("model_state='thesis' cannot give a policy that observes 'full'; use model_state='full'")
        state_columns = observation_columns(robot, model_state)
        policy_columns = observation_columns(robot, observation)
        position = {int(c): i for i, c in enumerate(state_columns)}
        joint_values = 2 * len(robot.actuated) if model_state == "full" else 0
        bodies = (len(state_columns) - joint_values) // VALUES_PER_BODY
        return cls(bodies, joint_values, tuple(int(c) for c in state_columns),
                   tuple(position[int(c)] for c in policy_columns), append_design)

    @property
    def robot_size(self) -> int:
        """The robot's own state: bodies, then joint values (what the env reports)."""
        return self.num_bodies * VALUES_PER_BODY + self.num_joint_values

    @property
    def feature_size(self) -> int:
        return self.robot_size - 2

    @property
    def observation_size(self) -> int:
        return len(self.observation_columns) + (2 if self.append_design else 0)

    @property
    def observation_shape(self) -> tuple[int, ...]:
        """The shape of one robot's :meth:`observation`."""
        return (self.observation_size,)

    @property
    def position_columns(self) -> list[int]:
        """Body positions and joint angles: what the thesis' position network predicts."""
        bodies = [VALUES_PER_BODY * b + k for b in range(self.num_bodies) for k in range(3)]
        joints = self.robot_size - self.num_joint_values
        return bodies + list(range(joints, joints + self.num_joint_values // 2))

    @property
    def velocity_columns(self) -> list[int]:
        """Body velocities and joint rates: what the thesis' velocity network predicts."""
        positions = set(self.position_columns)
        return [c for c in range(self.robot_size) if c not in positions]

    def from_full(self, full_state: torch.Tensor) -> torch.Tensor:
        """The robot's part of the model's state out of the env's ``full`` layout (no memory)."""
        if full_state.shape[-1] == self.robot_size:
            return full_state
        return full_state[..., list(self.state_columns)]

    def features(self, state: torch.Tensor) -> torch.Tensor:
        """Translation-invariant features ``[..., size - 2]``: base x, y dropped, other bodies' x, y relative to it."""
        bodies = state[..., : self.num_bodies * VALUES_PER_BODY].unflatten(-1, (self.num_bodies, VALUES_PER_BODY))
        base_xy = bodies[..., :1, :2]
        relative = torch.cat([bodies[..., :2] - base_xy, bodies[..., 2:]], dim=-1)
        # The base's own relative x, y are zero by construction: leave them out.
        flat = relative.flatten(-2)[..., 2:]
        return torch.cat([flat, state[..., self.num_bodies * VALUES_PER_BODY:self.robot_size]], dim=-1)

    def state_names(self, body_names: tuple[str, ...] | None = None) -> list[str]:
        """A name per robot state column: ``<body>.x`` .. ``<body>.vz`` per body (``body_names``, or
        ``base``, ``body1``, ...), then ``joint<j>.angle`` per actuated joint and ``joint<j>.rate``."""
        if body_names is None:
            body_names = ("base", *(f"body{b}" for b in range(1, self.num_bodies)))
        if len(body_names) != self.num_bodies:
            raise ValueError(f"the layout has {self.num_bodies} bodies, got {len(body_names)} names")
        values = ("x", "y", "z", "vx", "vy", "vz")
        joints = self.num_joint_values // 2
        return ([f"{body}.{value}" for body in body_names for value in values]
                + [f"joint{j}.angle" for j in range(joints)] + [f"joint{j}.rate" for j in range(joints)])

    def feature_names(self, body_names: tuple[str, ...] | None = None) -> list[str]:
        """A name per column of :meth:`features`, read off :meth:`features` itself (so the two
        cannot drift apart): the state column it takes, ``rel.`` in front where the base's is
        subtracted."""
        names = self.state_names(body_names)
        # Column k of features(I) is feature k as a combination of the state columns.
        weights = self.features(torch.eye(self.robot_size))
        return [("rel." if (column < 0).any() else "") + names[int(column.argmax())] for column in weights.T]

    def observation(self, state: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """The policy's observation of ``state`` (and ``design`` when the env appends it)."""
        observation = state[..., list(self.observation_columns)]
        return torch.cat([observation, design.to(observation.dtype)], dim=-1) if self.append_design else observation
