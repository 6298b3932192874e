"""Environment throughput: how close each env comes to raw PyBullet speed on the same robot.

    python benchmarks/env_throughput.py [--actions 3000] [--repeats 3]

Every variant runs the DE robot, 16 physics steps per action, uniform random actions,
100-action episodes (the envs rebuild the robot at every reset, as training does; the
raw loop only steps). Prints actions/s (median of the repeats) and each ratio to the
raw loop; the last line is ``env_throughput_ratio: <batched N=32 / raw>``.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time

import numpy as np
import pybullet
import torch
from torchrl.envs import ParallelEnv

from unipolicy_rl.envs import BatchedWalkerEnv, DesignDistribution, PhysicsSettings, RobotSettings, WalkerEnv
from unipolicy_rl.robots import load_robot, standing_height

DE = DesignDistribution.fixed(0.175, 0.5)


def raw_pybullet(actions: int) -> float:
    """The physics limit: motor command plus 16 stepSimulation calls per action, nothing else."""
    physics, robot = PhysicsSettings(), RobotSettings()
    client = pybullet.connect(pybullet.DIRECT)
    pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
    pybullet.setPhysicsEngineParameter(fixedTimeStep=physics.time_step, physicsClientId=client)
    pybullet.createMultiBody(0, pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client),
                             physicsClientId=client)
    description = robot.describe(DE.mean)
    body = load_robot(client, description, (0, 0, standing_height(description) + 0.005), np.pi, physics.max_torque)
    n = len(body.actuated_joint_indices)
    targets = np.random.default_rng(0).uniform(-1.5, 1.5, (actions, n)).tolist()
    start = time.perf_counter()
    for target in targets:
        pybullet.setJointMotorControlArray(
            body.body_id, body.actuated_joint_indices, pybullet.POSITION_CONTROL, targetPositions=target,
            forces=[physics.max_torque] * n, positionGains=[physics.position_gain] * n,
            velocityGains=[physics.velocity_gain] * n, physicsClientId=client,
        )
        for _ in range(physics.substeps):
            pybullet.stepSimulation(physicsClientId=client)
    elapsed = time.perf_counter() - start
    pybullet.disconnect(client)
    return actions / elapsed


def gymnasium_env(actions: int) -> float:
    env = WalkerEnv(DE)
    env.reset(seed=0)
    samples = np.random.default_rng(0).uniform(-1, 1, (actions, 4))
    start = time.perf_counter()
    for action in samples:
        if env.step(action)[3]:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return actions / elapsed


def torchrl_env(make_env, actions: int) -> float:
    env = make_env()
    env.set_seed(0)
    steps = max(1, actions // env.batch_size.numel())
    env.rollout(2, break_when_any_done=False)  # warm-up: worker start, first resets
    start = time.perf_counter()
    env.rollout(steps, break_when_any_done=False)
    elapsed = time.perf_counter() - start
    env.close()
    return steps * env.batch_size.numel() / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--actions", type=int, default=3000, help="actions per variant and repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)

    variants = {
        "raw PyBullet loop": raw_pybullet,
        "WalkerEnv (gymnasium)": gymnasium_env,
        **{
            f"BatchedWalkerEnv N={n}": functools.partial(torchrl_env, functools.partial(BatchedWalkerEnv, n, DE))
            for n in (1, 8, 32)
        },
        "ParallelEnv 2 workers x N=16": functools.partial(
            torchrl_env,
            lambda: ParallelEnv(2, functools.partial(BatchedWalkerEnv, 16, DE), mp_start_method="fork"),
        ),
    }
    rates = {name: [] for name in variants}
    for _ in range(args.repeats):  # interleave repeats so drift in machine load hits every variant
        for name, run in variants.items():
            rates[name].append(run(args.actions))
    medians = {name: statistics.median(values) for name, values in rates.items()}
    raw = medians["raw PyBullet loop"]
    print(f"{'variant':32s} {'actions/s':>10s} {'x raw':>7s}")
    for name, rate in medians.items():
        print(f"{name:32s} {rate:10.0f} {rate / raw:7.3f}")
    single = medians["BatchedWalkerEnv N=32"]
    parallel = medians["ParallelEnv 2 workers x N=16"]
    print(f"ParallelEnv (2 cores) / BatchedWalkerEnv N=32 (1 core): {parallel / single:.3f}")
    print(f"env_throughput_ratio: {single / raw:.3f}")


if __name__ == "__main__":
    main()
