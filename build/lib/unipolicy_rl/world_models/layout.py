"""What a world model's state vector holds, and the views of it a model and a policy need.

The state is one of the env's observation layouts without the design: per body (the base
first) position xyz then velocity xyz, then, in the ``full`` layout, the actuated joints'
angles and rates. Two views are derived here and nowhere else:

* the model's input features, translation invariant: the base's x, y are dropped and every
  other body's x, y are taken relative to the base, so a gait learned at x = 0 holds at
  x = 3 m (MBPO/ME-TRPO remove positions from the input for the same reason);
* the policy's observation: the columns of the env's ``observation`` layout within the state
  (:func:`~unipolicy_rl.envs.simulation.observation_columns`), with (l, rho) appended when
  the env appends them, so the policy sees exactly what the real env would show it.

A model whose prediction needs more than the robot's state (the thesis' ME-PCE needs the step
within the episode and the last actions) carries it as ``memory_size`` columns after the
robot's state; the model fills them (``Dynamics.memory_of``), the env only passes them on.

The keys (:attr:`StateLayout.state_key`, ``observation_key``, ``build_keys``) say where the
replay buffer reads the state and what the imagined env writes for the policy; the link-token
layout of a grammar robot (:class:`~unipolicy_rl.world_models.token_layout.TokenLayout`) has
the same members with other keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from unipolicy_rl.envs.simulation import OBSERVATIONS, RobotSettings, observation_columns

VALUES_PER_BODY = 6  # position xyz, velocity xyz


@dataclass(frozen=True)
class StateLayout:
    """Indices into a state of ``size`` numbers: ``num_bodies`` bodies then ``num_joint_values``.

    ``state_columns`` place the state within the env's ``full`` layout (the ``state`` key of a
    ``BatchedWalkerEnv(full_state=True)``); ``observation_columns`` place the policy's
    observation within the state.
    """

    # The env key the robot's state is read from (a ``BatchedWalkerEnv(full_state=True)``'s).
    state_key: ClassVar[str] = "state"
    # The key the policy reads (:meth:`observation`), and the keys of the robot's build that an
    # imagined step carries unchanged from its start state (none: one robot, one build).
    observation_key: ClassVar[str] = "observation"
    build_keys: ClassVar[tuple[str, ...]] = ()

    num_bodies: int
    num_joint_values: int
    state_columns: tuple[int, ...]
    observation_columns: tuple[int, ...]
    append_design: bool = False
    memory_size: int = 0

    @classmethod
    def for_env(cls, robot: RobotSettings, observation: str, append_design: bool, model_state: str) -> StateLayout:
        """The layout of a model that predicts ``model_state`` for a policy that observes ``observation``.

        ``model_state`` may be richer than ``observation`` (``full`` for a ``thesis`` policy),
        never poorer: the policy's inputs must be derivable from what the model predicts.
        """
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
    def size(self) -> int:
        """The robot's state and the model's memory after it."""
        return self.robot_size + self.memory_size

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
