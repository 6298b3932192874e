"""How many robots the grammar derives up to each size, how many stand, and whether standing holds in PyBullet.

    python study/scripts/grammar_census.py [--samples 200] [--seed 0] [--physics 60] [--split-seed 0]

Counts are exact (``count_morphologies``: every robot has one derivation). The share that
stands is exact over every robot of the smallest sizes (two segments, one or two leg pairs
of one-link legs) and estimated elsewhere from ``--samples`` seeded draws per size
(``sample_morphology`` at that size), each robot judged at both ends of the SE length range.

``--physics N`` drops N robots the filter passes and N it rejects onto the ground in PyBullet,
every hinge held at its rest angle by the env's PD motors (``PhysicsSettings``), and checks
after 2 s whether the base kept its rest orientation (within 10 degrees) and height (within
2 cm): the static filter's claim, tested in the dynamics (the env simulates no self-collision,
so a robot rejected for one can still hold its pose). Last, the default split is drawn and
timed (``--split-seed``).
"""

from __future__ import annotations

import argparse
import collections
import math
import time

import numpy as np
import pybullet

from unipolicy_rl.envs.design import SE_LENGTH_RANGE
from unipolicy_rl.envs.simulation import PhysicsSettings
from unipolicy_rl.robots import load_robot
from unipolicy_rl.robots.grammar import (
    SizeLimits,
    count_morphologies,
    derive,
    describe,
    enumerate_morphologies,
    sample_morphology,
    split_morphologies,
    stance,
)
from unipolicy_rl.robots.kinematics import rest_height

LIMITS = SizeLimits(segments=(2, 5), leg_pairs=(1, 3), limb_links=(1, 3))


def judge(morphology) -> str | None:
    """Why the robot fails to stand at either end of the length range (None when it stands at both)."""
    graph = derive(morphology.derivation())
    for length in SE_LENGTH_RANGE:
        failure = stance(describe(graph, length=length)).failure()
        if failure:
            return failure
    return None


def reason(failure: str | None) -> str:
    if failure is None:
        return "stands"
    return {"self-collision": "self-collision", "rests": "point/line support", "centre": "CoM off the support"}[
        failure.split()[0]]


def holds_rest(description, physics: PhysicsSettings, seconds: float = 2.0) -> bool:
    """Whether the robot, dropped from 2 mm above its rest height with every hinge held at zero,
    keeps its base's orientation within 10 degrees and its height within 2 cm."""
    height = rest_height(description) + 0.002
    client = pybullet.connect(pybullet.DIRECT)
    try:
        pybullet.setPhysicsEngineParameter(fixedTimeStep=physics.time_step, physicsClientId=client)
        pybullet.setGravity(0.0, 0.0, -9.81, physicsClientId=client)
        plane = pybullet.createMultiBody(0.0, pybullet.createCollisionShape(pybullet.GEOM_PLANE,
                                                                            physicsClientId=client),
                                         physicsClientId=client)
        pybullet.changeDynamics(plane, -1, lateralFriction=physics.lateral_friction, physicsClientId=client)
        body = load_robot(client, description, (0.0, 0.0, height), math.pi, physics.max_torque)
        joints = body.actuated_joint_indices
        pybullet.setJointMotorControlArray(
            body.body_id, joints, pybullet.POSITION_CONTROL, targetPositions=[0.0] * len(joints),
            forces=[physics.max_torque] * len(joints), positionGains=[physics.position_gain] * len(joints),
            velocityGains=[physics.velocity_gain] * len(joints), physicsClientId=client)
        _, start_turn = pybullet.getBasePositionAndOrientation(body.body_id, physicsClientId=client)
        for _ in range(int(seconds / physics.time_step)):
            pybullet.stepSimulation(physicsClientId=client)
        position, turn = pybullet.getBasePositionAndOrientation(body.body_id, physicsClientId=client)
    finally:
        pybullet.disconnect(client)
    relative = pybullet.getDifferenceQuaternion(start_turn, turn)
    tilt = 2.0 * math.degrees(math.acos(min(1.0, abs(relative[3]))))
    return tilt < 10.0 and abs(position[2] - height) < 0.02


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=200, help="draws per size for the standing share")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--physics", type=int, default=60, help="robots per side of the filter to simulate")
    parser.add_argument("--split-seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)

    for pairs in (1, 2):
        smallest = SizeLimits(segments=(2, 2), leg_pairs=(pairs, pairs), limb_links=(1, 1))
        exact = collections.Counter(reason(judge(m)) for m in enumerate_morphologies(smallest))
        print(f"exact, 2 segments, {pairs} leg pair(s) of 1-link legs: {count_morphologies(smallest)} robots, "
              f"{dict(exact)}")

    print("| segments | leg pairs | derivations | stand | self-collision | point/line support | CoM off the support |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    standing, falling = [], []
    for segments in range(LIMITS.segments[0], LIMITS.segments[1] + 1):
        for pairs in LIMITS.pair_counts(segments):
            size = SizeLimits((segments, segments), (pairs, pairs), LIMITS.limb_links)
            tally = collections.Counter()
            for _ in range(args.samples):
                morphology = sample_morphology(rng, size)
                verdict = reason(judge(morphology))
                tally[verdict] += 1
                (standing if verdict == "stands" else falling).append(morphology)
            shares = [f"{100 * tally[key] / args.samples:.1f}%" for key in
                      ("stands", "self-collision", "point/line support", "CoM off the support")]
            print(f"| {segments} | {pairs} | {count_morphologies(size):.3g} | " + " | ".join(shares) + " |")
    print(f"all sizes: {count_morphologies(LIMITS):.4g} derivations")

    if args.physics:
        physics = PhysicsSettings()
        picks = np.random.default_rng(args.seed + 1)
        for name, pool in (("filter passes", standing), ("filter rejects", falling)):
            chosen = [pool[i] for i in picks.choice(len(pool), size=min(args.physics, len(pool)), replace=False)]
            held, tried = collections.Counter(), collections.Counter()
            for morphology in chosen:
                verdict = reason(judge(morphology))
                tried[verdict] += 1
                held[verdict] += holds_rest(describe(morphology.derivation(),
                                                     length=float(np.mean(SE_LENGTH_RANGE))), physics)
            detail = ", ".join(f"{verdict} {held[verdict]}/{tried[verdict]}" for verdict in sorted(tried))
            print(f"physics, {name}: {sum(held.values())} of {len(chosen)} keep their rest pose for 2 s ({detail})")

    start = time.perf_counter()
    split = split_morphologies(args.split_seed, SE_LENGTH_RANGE)
    elapsed = time.perf_counter() - start
    print(f"default split (seed {args.split_seed}): {len(split.train)} training, {len(split.held_out)} held out "
          f"({len(split.larger_held_out)} larger than any training robot) in {elapsed:.1f} s")
    print("training sizes (segments, leg pairs):", sorted(collections.Counter(
        (m.segments, m.leg_pairs) for m in split.train).items()))
    print("held-out sizes:", sorted(collections.Counter((m.segments, m.leg_pairs) for m in split.held_out).items()))


if __name__ == "__main__":
    main()
