"""One robot in one PyBullet client: build a design, drive its motors, read its state.

Both the gymnasium env and the batched TorchRL env step robots through this class, so
there is a single place where physics settings, observations and fault handling live.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pybullet

from unipolicy_rl.envs.design import Design
from unipolicy_rl.envs.limits import healthy_rows
from unipolicy_rl.robots import (
    DEFAULT_ACTUATED,
    RobotBody,
    RobotDescription,
    load_robot,
    standing_height,
    vertebrate,
)
from unipolicy_rl.robots.urdf import JOINT_RANGE

OBSERVATIONS = ("thesis", "full")


@dataclass(frozen=True)
class PhysicsSettings:
    """Simulation and low-level control: 240 Hz physics, one action per 16 physics steps,
    joint targets tracked by PyBullet's PD position motor (gains and torque limit)."""

    time_step: float = 1.0 / 240.0
    substeps: int = 16
    # Stiffer than the thesis' 0.05 / 0.1 and stronger than RoboGrammar's 1 N m: with
    # those, the long heavy corner of the SE range (l=0.2, rho=0.6) cannot hold its weight.
    position_gain: float = 0.3
    velocity_gain: float = 1.0
    max_torque: float = 1.5
    action_range: float = JOINT_RANGE
    lateral_friction: float = 1.0
    # The position motors' top speed (rad/s), a servo's speed limit; None: none. Without one a
    # motor drives a light link as fast as its torque allows: some of the grammar's robots then
    # fling themselves metres into the air (docs/grammar.md). The vertebrate runs without.
    max_joint_speed: float | None = None

    def __post_init__(self) -> None:
        if not (self.time_step > 0 and math.isfinite(self.time_step)):
            raise ValueError(f"time_step must be positive, got {self.time_step!r}")
        if not (isinstance(self.substeps, int) and self.substeps >= 1):
            raise ValueError(f"substeps must be a positive integer, got {self.substeps!r}")
        for name in ("position_gain", "velocity_gain", "max_torque", "lateral_friction"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")
        if not 0 < self.action_range <= JOINT_RANGE:
            raise ValueError(f"action_range must lie in (0, {JOINT_RANGE}] rad, got {self.action_range!r}")
        if self.max_joint_speed is not None and not (self.max_joint_speed > 0 and math.isfinite(self.max_joint_speed)):
            raise ValueError(f"max_joint_speed must be null or a positive finite number (rad/s), "
                             f"got {self.max_joint_speed!r}")

    @property
    def control_period(self) -> float:
        return self.time_step * self.substeps


@dataclass(frozen=True)
class RobotSettings:
    """Which robot and which of its hinges the policy drives (the rest are locked)."""

    actuated: tuple[str, ...] = DEFAULT_ACTUATED
    knee_angle_deg: float = 60.0
    # The thesis observes the base and "the two outermost leg links": we take the front
    # and rear left-right diagonal's feet, which see both phases of a trotting gait.
    observed_links: tuple[str, ...] = ("front_left_shin", "rear_right_shin")

    def __post_init__(self) -> None:
        object.__setattr__(self, "actuated", tuple(self.actuated))
        object.__setattr__(self, "observed_links", tuple(self.observed_links))
        if not self.actuated:
            raise ValueError("at least one joint must be actuated")
        description = self.describe(Design(0.175, 0.5))
        for name in self.observed_links:
            description.link(name)

    def describe(self, design: Design):
        return vertebrate(design.length, design.density, self.actuated, self.knee_angle_deg)


def observation_columns(robot: RobotSettings, observation: str) -> np.ndarray:
    """Where each number of an ``observation`` layout sits in the ``full`` layout.

    ``full`` reads every link and the actuated joints; ``thesis`` reads the base and
    ``robot.observed_links`` in the same per-body order (position xyz, velocity xyz), so it
    is a column selection of ``full``. A world model that predicts the full state derives the
    policy's observation with these columns, the same numbers the real env would report.
    """
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")
    links = [link.name for link in robot.describe(Design(0.175, 0.5)).links]
    full_size = 6 * len(links) + 2 * len(robot.actuated)
    if observation == "full":
        return np.arange(full_size)
    bodies = [0] + [links.index(name) for name in robot.observed_links]
    return np.array([6 * body + k for body in bodies for k in range(6)])


def joint_targets(actions: np.ndarray, action_range: float) -> np.ndarray:
    """Maps actions in [-1, 1] (clipped) to joint targets within +-action_range of the initial pose.

    The initial pose has every joint at zero, so the target is the scaled action; works
    on one action or a batch at once.
    """
    actions = np.asarray(actions, dtype=np.float64)
    if not np.isfinite(actions).all():
        raise ValueError(f"actions must be finite, got {actions!r}")
    return action_range * np.clip(actions, -1.0, 1.0)


def build_world(client: int, physics: PhysicsSettings, description: RobotDescription, height: float,
                visuals: bool = False) -> RobotBody:
    """A fresh world in ``client``: gravity, a plane, and the robot with its base ``height`` (+5 mm)
    above the ground at the origin, facing +x; every link with the ground's friction.

    A fresh world for every build: Bullet's results depend on the order bodies were added and
    removed, so rebuilding from scratch makes an episode a function of its robot and actions alone
    (reproducible after a resume, comparable across runs).
    """
    pybullet.resetSimulation(physicsClientId=client)
    pybullet.setPhysicsEngineParameter(fixedTimeStep=physics.time_step, physicsClientId=client)
    pybullet.setGravity(0.0, 0.0, -9.81, physicsClientId=client)
    ground = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
    plane = pybullet.createMultiBody(0.0, ground, physicsClientId=client)
    pybullet.changeDynamics(plane, -1, lateralFriction=physics.lateral_friction, physicsClientId=client)
    body = load_robot(client, description, (0.0, 0.0, height + 0.005), math.pi, physics.max_torque, visuals)
    for link_index in body.link_indices.values():
        pybullet.changeDynamics(body.body_id, link_index, lateralFriction=physics.lateral_friction,
                                physicsClientId=client)
    return body


def position_motors(body: RobotBody, physics: PhysicsSettings) -> dict:
    """Keyword arguments of ``setJointMotorControlArray`` for ``body``'s actuated joints, less the
    targets: PyBullet's PD position motors with the physics settings' gains and torque limit
    (:func:`drive` sets the targets, and the speed limit where there is one)."""
    n = len(body.actuated_joint_indices)
    return {
        "bodyUniqueId": body.body_id,
        "jointIndices": body.actuated_joint_indices,
        "controlMode": pybullet.POSITION_CONTROL,
        "forces": [physics.max_torque] * n,
        "positionGains": [physics.position_gain] * n,
        "velocityGains": [physics.velocity_gain] * n,
        "physicsClientId": body.client,
    }


def drive(motors: dict, targets: Sequence[float], max_speed: float | None) -> None:
    """Sets the position motors' targets (``motors`` from :func:`position_motors`): one call for
    every joint, or, with a speed limit, which PyBullet's array call cannot take, one call per joint
    with ``maxVelocity``. (``changeDynamics(maxJointVelocity=...)`` is not a substitute: it clamps
    the joint's state and flings the robots instead, docs/grammar.md.)"""
    if max_speed is None:
        pybullet.setJointMotorControlArray(targetPositions=targets, **motors)
        return
    body, client = motors["bodyUniqueId"], motors["physicsClientId"]
    for joint, target, force, position_gain, velocity_gain in zip(
            motors["jointIndices"], targets, motors["forces"], motors["positionGains"], motors["velocityGains"],
            strict=True):
        pybullet.setJointMotorControl2(body, joint, pybullet.POSITION_CONTROL, targetPosition=target, force=force,
                                       positionGain=position_gain, velocityGain=velocity_gain, maxVelocity=max_speed,
                                       physicsClientId=client)


class WalkerSimulation:
    """A PyBullet DIRECT client holding a plane and one robot of the current design."""

    def __init__(self, robot: RobotSettings, physics: PhysicsSettings, observation: str = "thesis",
                 visuals: bool = False):
        if observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")
        self.robot_settings = robot
        self.physics = physics
        self.observation_kind = observation
        self.visuals = visuals
        self.num_actions = len(robot.actuated)
        template = robot.describe(Design(0.175, 0.5))
        self._link_names = [link.name for link in template.links]
        self.observation_size = 6 * (1 + len(robot.observed_links)) if observation == "thesis" else (
            6 * len(self._link_names) + 2 * self.num_actions
        )
        # Each observed body (the base, then links) contributes position xyz and velocity xyz.
        positions_per_observation = 1 + (len(robot.observed_links) if observation == "thesis"
                                         else len(self._link_names) - 1)
        self._xy_columns = np.array([6 * k + axis for k in range(positions_per_observation) for axis in (0, 1)])
        self.client = pybullet.connect(pybullet.DIRECT)
        self.body: RobotBody | None = None
        self.design: Design | None = None
        self.start_offset = np.zeros(self.observation_size)
        self.last_observation = np.zeros(self.observation_size)

    # -- lifecycle -----------------------------------------------------------------
    def reset(self, design: Design) -> np.ndarray:
        """Puts a robot of ``design`` standing at the origin, facing +x.

        A new design rebuilds the body. The same design a second time (always, under DE)
        rebuilds it once more and saves that state; every later time restores it, which is
        several times cheaper. Saving only on a repeat keeps the save off the SE path, where
        designs never repeat.
        """
        repeat = self.body is not None and design == self.design
        if repeat and self._built_state is not None:
            pybullet.restoreState(self._built_state, physicsClientId=self.client)
        else:
            self._build(design)
            if repeat:
                self._built_state = pybullet.saveState(physicsClientId=self.client)
        self._drive([0.0] * self.num_actions)
        base_position, _ = pybullet.getBasePositionAndOrientation(self.body.body_id, physicsClientId=self.client)
        # Positions are measured from where the base started, as in the thesis' fixed global
        # frame: the observation is the world-frame state minus this offset (x, y only).
        self.start_offset = np.zeros(self.observation_size)
        self.start_offset[self._xy_columns] = np.tile(base_position[:2], len(self._xy_columns) // 2)
        self.last_observation = self.read()
        return self.last_observation.copy()

    def _build(self, design: Design) -> None:
        description = self.robot_settings.describe(design)
        self.body = build_world(self.client, self.physics, description, standing_height(description), self.visuals)
        self.design = design
        observed = self.robot_settings.observed_links if self.observation_kind == "thesis" else self._link_names[1:]
        self._read_links = [self.body.link_index(name) for name in observed]
        self._motor_command = position_motors(self.body, self.physics)
        self._built_state: int | None = None

    def close(self) -> None:
        if self.client is not None and pybullet.isConnected(self.client):
            pybullet.disconnect(self.client)
        self.client = None

    # -- stepping ------------------------------------------------------------------
    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool]:
        """Applies one action for ``substeps`` physics steps; returns (observation, faulted).

        A faulted step (non-finite or exploding state) returns the last good observation,
        so no NaN ever reaches a policy or a replay buffer; the caller ends the episode.
        """
        self.advance(joint_targets(action, self.physics.action_range).tolist())
        observation = self.read()
        if not healthy_rows(observation):
            return self.last_observation.copy(), True
        self.last_observation = observation
        return observation, False

    def advance(self, targets: Sequence[float]) -> None:
        """Sets the motor targets (rad, one per actuated joint) and runs one control period of physics.

        Takes plain floats: a batch converts its whole target array to lists once
        (``ndarray.tolist``) instead of once per robot.
        """
        self._drive(targets)
        for _ in range(self.physics.substeps):
            pybullet.stepSimulation(physicsClientId=self.client)

    def _drive(self, targets: Sequence[float]) -> None:
        drive(self._motor_command, targets, self.physics.max_joint_speed)

    # -- state ---------------------------------------------------------------------
    def read(self) -> np.ndarray:
        """The current observation, unchecked (see :func:`healthy_rows`)."""
        return np.subtract(self.world_state(), self.start_offset)

    def world_state(self) -> list[float]:
        """The observation's values with positions in the world frame, as PyBullet gives them.

        Subtracting :attr:`start_offset` gives the observation. A plain list, so a batch of
        robots becomes one array in one conversion.
        """
        body, client = self.body.body_id, self.client
        position, _ = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
        velocity, _ = pybullet.getBaseVelocity(body, physicsClientId=client)
        # Forward kinematics on read: otherwise link states lag the base by one physics step.
        states = pybullet.getLinkStates(body, self._read_links, computeLinkVelocity=1, computeForwardKinematics=1,
                                        physicsClientId=client)
        values = [*position, *velocity]
        for state in states:
            values += [*state[0], *state[6]]
        if self.observation_kind == "full":
            joints = pybullet.getJointStates(body, self.body.actuated_joint_indices, physicsClientId=client)
            values += [joint[0] for joint in joints] + [joint[1] for joint in joints]
        return values

    def base_position(self) -> np.ndarray:
        """Base link position relative to its start (x, y) and its height (z)."""
        return self.last_observation[:3].copy()
