"""Builds a :class:`RobotDescription` into a PyBullet client and names its parts."""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass

import pybullet

from unipolicy_rl.robots.description import RobotDescription
from unipolicy_rl.robots.urdf import to_urdf


@dataclass(frozen=True)
class RobotBody:
    """A robot loaded in one PyBullet client: its body id and the indices we read and drive."""

    client: int
    body_id: int
    link_indices: dict[str, int]  # link name -> PyBullet link index (the base is -1)
    actuated_joint_indices: tuple[int, ...]

    def link_index(self, name: str) -> int:
        if name not in self.link_indices:
            raise ValueError(f"unknown link {name!r}; links are {sorted(self.link_indices)}")
        return self.link_indices[name]


def load_robot(
    client: int,
    description: RobotDescription,
    base_position: tuple[float, float, float],
    base_yaw: float,
    max_torque: float,
    visuals: bool = False,
) -> RobotBody:
    """Loads the robot through its URDF so the simulated body is exactly the exported one.

    Visual shapes are only needed to render; leaving them out makes loading much faster.
    """
    urdf = to_urdf(description, max_torque, visuals)
    handle, path = tempfile.mkstemp(suffix=".urdf", prefix="unipolicy_")
    try:
        with os.fdopen(handle, "w") as file:
            file.write(urdf)
        body_id = pybullet.loadURDF(
            path,
            basePosition=base_position,
            baseOrientation=pybullet.getQuaternionFromEuler((0.0, 0.0, base_yaw)),
            flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
            physicsClientId=client,
        )
    finally:
        os.unlink(path)
    link_indices = {description.base.name: -1}
    joint_indices = {}
    for index in range(pybullet.getNumJoints(body_id, physicsClientId=client)):
        info = pybullet.getJointInfo(body_id, index, physicsClientId=client)
        joint_indices[info[1].decode()] = index
        link_indices[info[12].decode()] = index
    actuated = tuple(joint_indices[joint.name] for joint in description.actuated_joints)
    return RobotBody(client, body_id, link_indices, actuated)
