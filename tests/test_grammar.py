"""Robots from the grammar: rules, derivations, the thesis robot as a derivation, enumeration, standing, split."""

import dataclasses
import itertools
import math

import numpy as np
import pybullet
import pytest

from unipolicy_rl.robots import DEFAULT_ACTUATED, load_robot, standing_height, vertebrate
from unipolicy_rl.robots.grammar import (
    RULES,
    VERTEBRATE,
    LimbLink,
    Morphology,
    SizeLimits,
    applicable_rules,
    apply_rule,
    count_morphologies,
    derive,
    describe,
    enumerate_morphologies,
    part_kinds,
    sample_morphology,
    split_morphologies,
    stance,
    stands,
    stands_at,
)
from unipolicy_rl.robots.grammar.derivation import RobotGraph
from unipolicy_rl.robots.grammar.morphology import LIMB_JOINT_RULES
from unipolicy_rl.robots.grammar.parts import link_kind, robogrammar_joint
from unipolicy_rl.robots.grammar.standing import segment_distances, self_collisions
from unipolicy_rl.robots.kinematics import rest_frames, rest_height, rest_segments, rpy_matrix

THESIS_LEG = VERTEBRATE.limbs[0]
ACUTE_KNEE_LEG = (THESIS_LEG[0], dataclasses.replace(THESIS_LEG[1], joint="make_acute_lift_limb_joint"))


def _grammar_names(name: str, knee: str) -> str:
    """The thesis robot's part names as the grammar names them."""
    for old, new in (("front_", "leg_0_"), ("rear_", "leg_1_"), ("thigh", "link_1"), ("shin", "link_2"),
                     ("hip", "axial_roll_1"), ("knee", f"{knee}_2")):
        name = name.replace(old, new)
    return name


@pytest.mark.parametrize(("length", "density", "knee_angle_deg", "leg", "knee"), [
    (0.175, 0.5, 60.0, THESIS_LEG, "obtuse_lift"),
    (0.15, 0.4, 60.0, THESIS_LEG, "obtuse_lift"),
    (0.20, 0.6, 120.0, ACUTE_KNEE_LEG, "acute_lift"),
])
def test_the_thesis_robot_is_a_derivation_link_for_link_and_joint_for_joint(length, density, knee_angle_deg, leg,
                                                                               knee):
    by_hand = vertebrate(length, density, knee_angle_deg=knee_angle_deg)
    morphology = dataclasses.replace(VERTEBRATE, limbs=(leg, (), leg))
    derived = describe(morphology.derivation(), length, density,
                       actuated=[_grammar_names(name, knee) for name in DEFAULT_ACTUATED])
    renamed_links = tuple(dataclasses.replace(link, name=_grammar_names(link.name, knee)) for link in by_hand.links)
    renamed_joints = tuple(
        dataclasses.replace(joint, name=_grammar_names(joint.name, knee), parent=_grammar_names(joint.parent, knee),
                            child=_grammar_names(joint.child, knee))
        for joint in by_hand.joints)
    assert derived.links == renamed_links
    assert len(derived.joints) == len(renamed_joints) == 14
    for ours, theirs in zip(derived.joints, renamed_joints, strict=True):
        assert (ours.name, ours.kind, ours.parent, ours.child, ours.actuated) == (
            theirs.name, theirs.kind, theirs.parent, theirs.child, theirs.actuated)
        assert ours.attach_fraction == theirs.attach_fraction
        assert ours.rpy == pytest.approx(theirs.rpy, abs=1e-12)
        assert ours.axis == pytest.approx(theirs.axis, abs=1e-12)


def test_the_thesis_robots_derivation_reads_structure_first_then_joints_head_to_tail():
    leg = ["make_long_limb_link", "append_limb_link", "make_long_limb_link", "end_limb"]
    joints = ["make_axial_roll_limb_joint", "make_obtuse_lift_limb_joint"]
    assert VERTEBRATE.derivation() == (
        "make_robot", "end_head", "make_body_with_legs", *leg, "append_body", "make_body_without_legs",
        "append_body", "make_body_with_legs", *leg, "end_tail",
        *joints, "make_roll_body_joint", "make_roll_body_joint", *joints)


def test_the_rule_set_is_robogrammars_twenty_and_the_thesis_hip():
    assert len(RULES) == 21
    assert set(LIMB_JOINT_RULES) == {f"make_{kind}_limb_joint" for kind in (
        "left_roll", "right_roll", "swing", "acute_lift", "obtuse_lift", "backwards_lift", "axial_roll")}


@pytest.mark.parametrize(("rule_name", "pointing"), [
    ("make_obtuse_lift_limb_joint", (math.cos(math.radians(60)), 0.0, -math.sin(math.radians(60)))),
    ("make_acute_lift_limb_joint", (math.cos(math.radians(120)), 0.0, -math.sin(math.radians(120)))),
    ("make_backwards_lift_limb_joint", (math.cos(math.radians(60)), 0.0, math.sin(math.radians(60)))),
    ("make_left_roll_limb_joint", (0.0, 1.0, 0.0)),
    ("make_right_roll_limb_joint", (0.0, -1.0, 0.0)),
    ("make_axial_roll_limb_joint", (1.0, 0.0, 0.0)),
])
def test_limb_joints_turn_the_next_link_as_robogrammar_does(rule_name, pointing):
    """Lifts bend the next link down by 60 (obtuse) or 120 degrees (acute), or up (backwards);
    rolls turn it a quarter about the vertical. RoboGrammar's turn is the parent-to-child rotation
    Bullet takes, so the child turns the opposite way to its axis_angle."""
    (edge,) = RULES[rule_name].right_edges
    assert rpy_matrix(edge.joint.rpy)[:, 0] == pytest.approx(pointing, abs=1e-12)


def test_a_leg_pair_is_mirrored_across_the_sagittal_plane():
    rng = np.random.default_rng(3)
    for _ in range(20):
        robot = describe(sample_morphology(rng, SizeLimits()).derivation())
        starts, ends = rest_segments(robot)
        names = [link.name for link in robot.links]
        for index, name in enumerate(names):
            if "_left" in name:
                mirror = names.index(name.replace("_left", "_right"))
                assert starts[mirror] == pytest.approx(starts[index] * [1, -1, 1], abs=1e-12)
                assert ends[mirror] == pytest.approx(ends[index] * [1, -1, 1], abs=1e-12)


def test_rest_frames_match_pybullets_link_frames():
    """The filter's kinematics and the simulated body (through the URDF) agree for grammar robots."""
    rng = np.random.default_rng(5)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        for _ in range(3):
            robot = describe(sample_morphology(rng, SizeLimits()).derivation(), 0.18, 0.5)
            body = load_robot(client, robot, (0.0, 0.0, 0.0), 0.0, 1.0)
            origins, rotations = rest_frames(robot)
            for index, link in enumerate(robot.links[1:], start=1):
                state = pybullet.getLinkState(body.body_id, body.link_index(link.name), computeForwardKinematics=1,
                                              physicsClientId=client)
                turn = np.array(pybullet.getMatrixFromQuaternion(state[5])).reshape(3, 3)
                assert state[4] == pytest.approx(origins[index], abs=1e-6)
                assert turn == pytest.approx(rotations[index], abs=1e-6)
            assert len(body.actuated_joint_indices) == len(robot.hinges)
            pybullet.removeBody(body.body_id, physicsClientId=client)
    finally:
        pybullet.disconnect(client)


def test_a_derivation_is_applied_step_by_step_to_the_leftmost_nonterminal():
    graph = RobotGraph()
    assert applicable_rules(graph) == ("make_robot",)
    apply_rule(graph, "make_robot")
    assert applicable_rules(graph) == ("end_head",)
    apply_rule(graph, "end_head")
    assert applicable_rules(graph) == ("make_body_with_legs", "make_body_without_legs")
    assert derive(VERTEBRATE.derivation()).is_terminal


@pytest.mark.parametrize(("make", "message"), [
    (lambda: derive(["make_robot", "make_wings"]), "make_wings"),
    (lambda: derive("make_robot end_head"), "sequence of rule names, got the string 'make_robot end_head'"),
    (lambda: derive(["make_robot", "end_head", "make_body_without_legs"]), r"nonterminals \['body_joint', 'tail'\]"),
    (lambda: derive(["make_robot", "end_tail"]), "leftmost nonterminal is 'head'"),
    (lambda: derive([*VERTEBRATE.derivation(), "end_tail"]), "nothing is left to rewrite"),
    (lambda: describe(derive(["make_robot"], complete=False)), "still has nonterminals"),
    (lambda: describe(VERTEBRATE.derivation(), actuated=["front_left_hip"]), "front_left_hip"),
    (lambda: SizeLimits(segments=(0, 5)), r"segments .* got \(0, 5\)"),
    (lambda: SizeLimits(segments=(2, 2), leg_pairs=(3, 3)), r"leg_pairs \(3, 3\)"),
    (lambda: SizeLimits(segments=(2, 3)).check(Morphology(((),) * 5, ("make_roll_body_joint",) * 4)),
     "5 body segments"),
    (lambda: Morphology(((),), ("make_roll_body_joint",)), "1 body segments need 0 body joints"),
    (lambda: LimbLink("make_elbow_limb_joint", "make_long_limb_link"), "make_elbow_limb_joint"),
    (lambda: Morphology((("make_long_limb_link",), ()), ("make_roll_body_joint",)), "'make_long_limb_link'"),
    (lambda: robogrammar_joint("tilted", "hinge", axis_angle=(1, 1, 0, 30)), r"\(1, 1, 0, 30\)"),
    (lambda: link_kind("wing"), "wing"),
    (lambda: split_morphologies(0, (0.15, 0.2), held_out_size=0), "held_out_size=0"),
    (lambda: split_morphologies(0, (0.15, 0.2), held_out_limits=SizeLimits((2, 4), (1, 2))), "no robot larger"),
])
def test_bad_input_names_the_problem(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_enumeration_matches_the_count_and_the_rewriting_engines_own_search():
    """Every morphology's derivation is one the engine reaches, and the engine reaches no other."""
    limits = SizeLimits(segments=(1, 2), leg_pairs=(0, 1), limb_links=(1, 1))
    enumerated = [morphology.derivation() for morphology in enumerate_morphologies(limits)]
    assert len(enumerated) == len(set(enumerated)) == count_morphologies(limits) == 1 + 14 + 4 + 2 * 14 * 4

    def search(prefix: list[str]):
        if prefix.count("append_body") > 1 or prefix.count("make_body_with_legs") > 1 or "append_limb_link" in prefix:
            return
        graph = derive(prefix, complete=False)
        if graph.is_terminal:
            yield tuple(prefix)
        for name in applicable_rules(graph):
            yield from search([*prefix, name])

    assert set(search([])) == set(enumerated)


def test_counts_grow_as_the_combinatorics_say():
    per_limb = sum(14**links for links in (1, 2, 3))
    assert count_morphologies(SizeLimits(), segments=2, leg_pairs=2) == per_limb**2 * 4
    assert count_morphologies(SizeLimits(), segments=5, leg_pairs=3) == math.comb(5, 3) * per_limb**3 * 4**4
    assert sum(count_morphologies(SizeLimits(), s, p) for s in range(2, 6) for p in range(1, 4)) == count_morphologies(
        SizeLimits())


def test_sampling_is_seeded_and_covers_the_limits():
    limits = SizeLimits(segments=(2, 5), leg_pairs=(1, 3), limb_links=(1, 3))
    first, again = np.random.default_rng(7), np.random.default_rng(7)
    assert [sample_morphology(first, limits) for _ in range(5)] == [sample_morphology(again, limits) for _ in range(5)]
    rng = np.random.default_rng(7)
    drawn = [sample_morphology(rng, limits) for _ in range(300)]
    assert all(limits.admits(morphology) for morphology in drawn)
    assert {(m.segments, m.leg_pairs) for m in drawn} == {
        (s, p) for s in range(2, 6) for p in range(1, min(3, s) + 1)}
    assert {links for m in drawn for links in m.limb_links} == {1, 2, 3}


def test_part_kinds_and_link_counts_follow_the_built_robot():
    rng = np.random.default_rng(3)
    limits = SizeLimits(segments=(2, 5), leg_pairs=(1, 3), limb_links=(1, 3))
    for morphology in [VERTEBRATE, *(sample_morphology(rng, limits) for _ in range(20))]:
        robot, kinds = describe(morphology.derivation()), part_kinds(morphology.derivation())
        assert len(kinds.links) == len(robot.links) == morphology.num_links
        assert len(kinds.joints) == len(robot.joints)
        for joint, joint_type in zip(robot.joints, kinds.joints, strict=True):
            assert joint_type in joint.name
    kinds = part_kinds(VERTEBRATE.derivation())
    assert kinds.links == ("body",) * 3 + ("limb_mount", "long_limb_link", "long_limb_link") * 4
    assert kinds.joints[:5] == ("roll", "roll", "mount", "axial_roll", "obtuse_lift")
    small = SizeLimits(segments=(1, 2), leg_pairs=(0, 1), limb_links=(1, 2))
    assert small.max_links == max(m.num_links for m in enumerate_morphologies(small)) == 2 + 2 * 3


def test_segment_distances_agree_with_a_dense_search():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 4, 3))
    points[:10, 3] = points[:10, 2] + (points[:10, 1] - points[:10, 0]) * 0.7  # parallel pairs
    distances = segment_distances(points[:, 0], points[:, 1], points[:, 2], points[:, 3])
    u = np.linspace(0.0, 1.0, 201)[:, None]
    for (p0, p1, q0, q1), distance in zip(points, distances, strict=True):
        dense = np.linalg.norm((p0 + u * (p1 - p0))[:, None] - (q0 + u * (q1 - q0))[None], axis=2).min()
        assert distance <= dense + 1e-9 and dense - distance < 2e-2


def test_self_collisions_are_the_overlaps_pybullet_finds_less_the_joints_own():
    """Bullet's own capsule distances at rest: every pair it finds overlapping is one the filter
    reports, or a pair the filter leaves out on purpose (a link and its parent, a leg pair's mounts)."""
    rng = np.random.default_rng(2)
    robots = [describe(Morphology((FOLDED_LEG, ()), ("make_fixed_body_joint",)).derivation()), vertebrate()]
    robots += [describe(sample_morphology(rng, SizeLimits(segments=(2, 3))).derivation()) for _ in range(4)]
    assert len(self_collisions(robots[0])) == 7 and not self_collisions(robots[1])
    client = pybullet.connect(pybullet.DIRECT)
    try:
        for robot in robots:
            body = load_robot(client, robot, (0.0, 0.0, 1.0), 0.0, 1.0)
            index = {link.name: body.link_index(link.name) for link in robot.links}
            joined = {frozenset((joint.parent, joint.child)) for joint in robot.joints}
            joined |= {frozenset((first.child, second.child)) for first, second in itertools.combinations(
                robot.joints, 2) if (first.parent, first.attach_fraction) == (second.parent, second.attach_fraction)}
            ours = {frozenset(pair) for pair in self_collisions(robot)}
            for a, b in itertools.combinations(index, 2):
                points = pybullet.getClosestPoints(body.body_id, body.body_id, 0.01, index[a], index[b],
                                                   physicsClientId=client)
                distance = min((point[8] for point in points), default=math.inf)
                pair = frozenset((a, b))
                if distance < -1e-4 and pair not in joined:
                    assert pair in ours, (robot.name, pair, distance)
                if pair in ours:
                    assert distance < 1e-4, (pair, distance)
            pybullet.removeBody(body.body_id, physicsClientId=client)
    finally:
        pybullet.disconnect(client)


@pytest.mark.parametrize("knee_angle_deg", [60.0, 120.0])
def test_rest_height_is_the_thesis_robots_standing_height(knee_angle_deg):
    robot = vertebrate(0.16, 0.5, knee_angle_deg=knee_angle_deg)
    assert rest_height(robot) == pytest.approx(standing_height(robot), abs=1e-12)


def test_the_thesis_robot_stands_on_four_feet():
    rest = stance(vertebrate())
    assert rest.stands() and rest.failure() is None
    assert len(rest.support) == 4
    assert rest.support_margin == pytest.approx(0.175)  # the feet span one link length either side of the CoM


FOLDED_LEG = (LimbLink("make_acute_lift_limb_joint", "make_long_limb_link"),) * 2
LEVEL_LEG = (LimbLink("make_axial_roll_limb_joint", "make_normal_limb_link"),)
TIPPING = Morphology(((LimbLink("make_acute_lift_limb_joint", "make_normal_limb_link"),
                       LimbLink("make_right_roll_limb_joint", "make_normal_limb_link")),
                      (LimbLink("make_axial_roll_limb_joint", "make_long_limb_link"),
                       LimbLink("make_right_roll_limb_joint", "make_normal_limb_link"))), ("make_swing_body_joint",))


@pytest.mark.parametrize(("morphology", "failure"), [
    (Morphology((FOLDED_LEG, ()), ("make_fixed_body_joint",)), "self-collision ('body_0', 'leg_0_left_link_2')"),
    (Morphology((LEVEL_LEG, ()), ("make_fixed_body_joint",)), "rests on a point or a line"),
    (TIPPING, "centre of mass -0.079 m from the support edge"),
])
def test_robots_that_do_not_stand_say_why(morphology, failure):
    robot = describe(morphology.derivation())
    assert stance(robot).failure() == failure
    assert not stands(robot)


def test_the_split_is_fixed_by_its_seed_and_holds_out_larger_robots():
    settings = {"lengths": (0.15, 0.20), "train_size": 4, "held_out_size": 2}
    split = split_morphologies(4, **settings)
    assert split == split_morphologies(4, **settings)
    assert split.train != split_morphologies(0, **settings).train
    assert len(split.train) == 4 and len(split.held_out) == 2
    assert not set(split.train) & set(split.held_out)
    assert len(split.larger_held_out) == 1
    most_segments = max(m.segments for m in split.train)
    most_pairs = max(m.leg_pairs for m in split.train)
    assert all(m.segments > most_segments or m.leg_pairs > most_pairs for m in split.larger_held_out)
    assert all(stands_at(m, settings["lengths"]) for m in itertools.chain(split.train, split.held_out))
