"""The robot description, its URDF and its PyBullet body."""

import math

import numpy as np
import pybullet
import pytest

from unipolicy_rl.envs import Design, RobotSettings, WalkerSimulation
from unipolicy_rl.envs.simulation import PhysicsSettings, joint_targets
from unipolicy_rl.robots import HINGES, Joint, Link, RobotDescription, vertebrate, write_urdf


def test_vertebrate_has_ten_hinges_four_actuated():
    robot = vertebrate()
    assert len(robot.hinges) == 10
    assert len(robot.actuated_joints) == 4
    assert len(robot.links) == 15
    assert set(HINGES) == {joint.name for joint in robot.hinges}


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Link("a", -0.1, 0.02, 0.5), "-0.1"),
        (lambda: Link("a", 0.1, 0.02, float("nan")), "nan"),
        (lambda: vertebrate(actuated=("front_left_elbow",)), "front_left_elbow"),
        (lambda: vertebrate(length=0.0), "0.0"),
        (lambda: Joint("j", "prismatic", "a", "b"), "prismatic"),
        (lambda: RobotDescription("r", (Link("a", 0.1, 0.02, 0.5),), (Joint("j", "fixed", "a", "ghost"),)), "ghost"),
    ],
)
def test_bad_descriptions_raise_naming_the_value(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def _masses_and_lengths(design: Design):
    simulation = WalkerSimulation(RobotSettings(), PhysicsSettings())
    simulation.reset(design)
    body, client = simulation.body.body_id, simulation.client
    indices = simulation.body.link_indices.values()
    masses = [pybullet.getDynamicsInfo(body, i, physicsClientId=client)[0] for i in indices]
    # Distance between consecutive body-link frames (joint origins) is one link length.
    body_1 = np.array(pybullet.getLinkState(body, simulation.body.link_index("body_1"), physicsClientId=client)[4])
    body_2 = np.array(pybullet.getLinkState(body, simulation.body.link_index("body_2"), physicsClientId=client)[4])
    simulation.close()
    return masses, float(np.linalg.norm(body_2 - body_1))


def test_design_shows_in_pybullet_masses_and_lengths():
    light_short, short = _masses_and_lengths(Design(0.15, 0.4))
    heavy_long, long = _masses_and_lengths(Design(0.20, 0.6))
    assert np.allclose(light_short, 0.15 * 0.4)
    assert np.allclose(heavy_long, 0.20 * 0.6)
    assert short == pytest.approx(0.15, abs=1e-6)
    assert long == pytest.approx(0.20, abs=1e-6)


def test_links_are_bare_capsules_with_the_cylinder_inertia_along_their_axis():
    """Each capsule sits at its link's centre of mass with no turn (else PyBullet wraps it in
    a compound shape, a slower world), and the inertia is still that of a cylinder along the
    link's x axis, as the description defines it."""
    design = Design(0.175, 0.5)
    simulation = WalkerSimulation(RobotSettings(), PhysicsSettings())
    simulation.reset(design)
    body, client = simulation.body.body_id, simulation.client
    description = simulation.robot_settings.describe(design)
    for link in description.links:
        index = simulation.body.link_index(link.name)
        (shape,) = pybullet.getCollisionShapeData(body, index, physicsClientId=client)
        assert shape[2] == pybullet.GEOM_CAPSULE
        assert shape[5] == pytest.approx((0, 0, 0)) and shape[6] == pytest.approx((0, 0, 0, 1))
        mass, _, diagonal, _, inertial_turn = pybullet.getDynamicsInfo(body, index, physicsClientId=client)[:5]
        turn = np.array(pybullet.getMatrixFromQuaternion(inertial_turn)).reshape(3, 3)
        in_link_frame = turn @ np.diag(diagonal) @ turn.T
        axial = 0.5 * mass * link.radius**2
        transverse = mass * (3 * link.radius**2 + link.length**2) / 12
        assert in_link_frame == pytest.approx(np.diag([axial, transverse, transverse]), abs=1e-9)
    simulation.close()


def test_urdf_export_loads_in_a_fresh_client(tmp_path):
    robot = vertebrate(0.18, 0.45)
    path = write_urdf(robot, tmp_path / "vertebrate.urdf")
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(path), flags=pybullet.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)
        num_joints = pybullet.getNumJoints(body, physicsClientId=client)
        masses = [pybullet.getDynamicsInfo(body, i, physicsClientId=client)[0] for i in range(-1, num_joints)]
        revolute = [
            pybullet.getJointInfo(body, i, physicsClientId=client)[1].decode()
            for i in range(num_joints)
            if pybullet.getJointInfo(body, i, physicsClientId=client)[2] == pybullet.JOINT_REVOLUTE
        ]
    finally:
        pybullet.disconnect(client)
    assert num_joints == len(robot.joints) == 14
    assert sum(masses) == pytest.approx(robot.total_mass) == pytest.approx(15 * 0.18 * 0.45)
    assert sorted(revolute) == sorted(joint.name for joint in robot.actuated_joints)


def test_locked_joints_do_not_move():
    """Random actuation for an episode: every locked hinge keeps its parent-child orientation."""
    simulation = WalkerSimulation(RobotSettings(), PhysicsSettings())
    simulation.reset(Design(0.175, 0.5))
    body, client = simulation.body.body_id, simulation.client
    description = simulation.robot_settings.describe(Design(0.175, 0.5))
    locked = [joint for joint in description.hinges if not joint.actuated]
    assert len(locked) == 6

    def relative_orientations():
        out = []
        for joint in locked:
            parent, child = (simulation.body.link_index(name) for name in (joint.parent, joint.child))
            parent_q = (pybullet.getBasePositionAndOrientation(body, physicsClientId=client)[1] if parent == -1
                        else pybullet.getLinkState(body, parent, computeForwardKinematics=1, physicsClientId=client)[5])
            child_q = pybullet.getLinkState(body, child, computeForwardKinematics=1, physicsClientId=client)[5]
            inverse = pybullet.invertTransform((0, 0, 0), parent_q)[1]
            out.append(pybullet.multiplyTransforms((0, 0, 0), inverse, (0, 0, 0), child_q)[1])
        return np.array(out)

    before = relative_orientations()
    rng = np.random.default_rng(0)
    moved = []
    for _ in range(40):
        simulation.step(rng.uniform(-1, 1, simulation.num_actions))
        moved.append(np.abs(np.abs(np.sum(before * relative_orientations(), axis=1)) - 1).max())
    simulation.close()
    assert max(moved) < 1e-6


def test_actions_are_clipped_to_the_joint_range():
    simulation = WalkerSimulation(RobotSettings(), PhysicsSettings())
    simulation.reset(Design(0.175, 0.5))
    targets = joint_targets(np.array([5.0, -7.0, 0.5, 1.0]), simulation.physics.action_range)
    assert targets == pytest.approx([1.5, -1.5, 0.75, 1.5])
    for _ in range(30):
        simulation.step(np.array([50.0, -50.0, 50.0, -50.0]))
    angles = [pybullet.getJointState(simulation.body.body_id, j, physicsClientId=simulation.client)[0]
              for j in simulation.body.actuated_joint_indices]
    simulation.close()
    assert max(abs(a) for a in angles) <= 1.5 + 0.05
    assert all(math.isfinite(a) for a in angles)
