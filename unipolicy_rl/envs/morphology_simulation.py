"""One robot of any description in one PyBullet client: build it, drive its motors, read every link.

:class:`~unipolicy_rl.envs.simulation.WalkerSimulation` holds one topology and reads the thesis'
observation; a robot of the grammar changes its body, its number of links and of joints from one
episode to the next, and is read link by link. Both build their worlds and drive their motors
through the same functions (:func:`~unipolicy_rl.envs.simulation.build_world`,
:func:`~unipolicy_rl.envs.simulation.position_motors`), so a robot is simulated alike in both.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pybullet

from unipolicy_rl.envs.simulation import PhysicsSettings, build_world, drive, position_motors
from unipolicy_rl.robots import RobotBody, RobotDescription
from unipolicy_rl.robots.kinematics import rest_height


class MorphologySimulation:
    """A PyBullet DIRECT client that holds a plane and the robot last :meth:`build` was given."""

    def __init__(self, physics: PhysicsSettings, visuals: bool = False):
        self.physics = physics
        self.visuals = visuals
        self.client = pybullet.connect(pybullet.DIRECT)
        self.body: RobotBody | None = None
        self.num_links = 0
        self.num_actions = 0
        self.base_inertial_rotation = np.eye(3)

    def build(self, description: RobotDescription) -> tuple[float, float]:
        """A fresh world with ``description`` standing at the origin facing +x, its motors holding
        every driven joint at zero; returns where its base stands (x, y)."""
        self.body = build_world(self.client, self.physics, description, rest_height(description), self.visuals)
        self.num_links = len(description.links)
        self.num_actions = len(self.body.actuated_joint_indices)
        self._links = [self.body.link_index(link.name) for link in description.links[1:]]
        self._motor_command = position_motors(self.body, self.physics)
        if self.num_actions:
            drive(self._motor_command, [0.0] * self.num_actions, self.physics.max_joint_speed)
        # PyBullet reports the base's inertial frame; the link's own frame (its +x along the
        # capsule, the frame joint axes are given in) is that frame turned back by this rotation.
        local = pybullet.getDynamicsInfo(self.body.body_id, -1, physicsClientId=self.client)[4]
        self.base_inertial_rotation = np.reshape(pybullet.getMatrixFromQuaternion(local), (3, 3))
        position, _ = pybullet.getBasePositionAndOrientation(self.body.body_id, physicsClientId=self.client)
        return position[0], position[1]

    def advance(self, targets: Sequence[float]) -> None:
        """Sets the driven joints' targets (rad, in the description's actuated-joint order) and runs
        one control period of physics."""
        if self.num_actions:
            drive(self._motor_command, targets, self.physics.max_joint_speed)
        for _ in range(self.physics.substeps):
            pybullet.stepSimulation(physicsClientId=self.client)

    def read(self) -> tuple[list[float], list[float]]:
        """Every link's world state (base first; per link its centre of mass, its orientation as a
        quaternion xyzw, linear and angular velocity: ``link_tokens.LINK_STATE_SIZE`` numbers) and
        each driven joint's (angle, rate), in plain lists so a batch converts once. A link's
        orientation is its own frame's; the base's is its inertial frame's (see
        :attr:`base_inertial_rotation`)."""
        body, client = self.body.body_id, self.client
        position, orientation = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
        linear, angular = pybullet.getBaseVelocity(body, physicsClientId=client)
        values = [*position, *orientation, *linear, *angular]
        if self._links:
            # Forward kinematics on read: otherwise link states lag the base by one physics step.
            for state in pybullet.getLinkStates(body, self._links, computeLinkVelocity=1, computeForwardKinematics=1,
                                                physicsClientId=client):
                values += [*state[0], *state[5], *state[6], *state[7]]
        joints: list[float] = []
        if self.num_actions:
            for joint in pybullet.getJointStates(body, self.body.actuated_joint_indices, physicsClientId=client):
                joints += [joint[0], joint[1]]
        return values, joints

    def close(self) -> None:
        if self.client is not None and pybullet.isConnected(self.client):
            pybullet.disconnect(self.client)
        self.client = None
