"""Environment throughput: how close each env comes to raw PyBullet speed on the same robot.

    python benchmarks/env_throughput.py [--actions 3000] [--repeats 3]

Every variant runs the DE robot, 16 physics steps per action, uniform random actions
drawn before timing, 100-action episodes on the same world (plane, friction, motors). The
raw loop is the physics alone: motor command, 16 ``stepSimulation`` calls, a state
restore per episode.
Prints actions/s (median of the repeats), each ratio to the raw loop and the share of a
core this process used (for a ParallelEnv: its parent), then the headline ratios, each
paired within a repeat: how two worker processes compare with one process (TorchRL's
stock ``ParallelEnv``, which spin-waits, and our ``SleepingParallelEnv``) and the
batched env at N=32 against the raw loop. The last line is
``env_throughput_ratio: <batched N=32 / raw, median of the paired ratios>``.
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

from unipolicy_rl.cpu_speed.parallel_env import SleepingParallelEnv
from unipolicy_rl.envs import (
    BatchedWalkerEnv,
    DesignDistribution,
    PhysicsSettings,
    RobotSettings,
    WalkerEnv,
    WalkerSimulation,
)

DE = DesignDistribution.fixed(0.175, 0.5)


class Stopwatch:
    """Wall time and this process's CPU time over a block. Their ratio is the share of a
    core the process used: about 1 for one process, and for a ``ParallelEnv`` parent the
    cost of its waiting (a spinning parent shows most of a core)."""

    def __enter__(self) -> Stopwatch:
        self.wall, self.cpu = -time.perf_counter(), -time.process_time()
        return self

    def __exit__(self, *exc_info) -> None:
        self.wall += time.perf_counter()
        self.cpu += time.process_time()

    def result(self, actions: int) -> tuple[float, float]:
        """(actions/s, share of a core used by this process)."""
        return actions / self.wall, self.cpu / self.wall


def raw_pybullet(actions: int, episode_length: int = 100, worlds: int = 1) -> tuple[float, float]:
    """The physics limit: motor command plus 16 stepSimulation calls per action, nothing else.

    The world (plane, robot, friction) is built by the env's own simulation class, untimed,
    so both sides simulate the same contacts; episodes end every ``episode_length``
    actions with a ``restoreState`` to the standing robot, as the envs' DE resets do.
    A robot that is never reset ends up lying still, which is cheaper to simulate.
    With ``worlds`` > 1 the actions go round that many clients, one robot each, as a
    batched env steps its robots: the same physics, minus everything the env adds.
    """
    physics = PhysicsSettings()
    simulations = [WalkerSimulation(RobotSettings(), physics) for _ in range(worlds)]
    for simulation in simulations:
        simulation.reset(DE.mean)
    clients = [simulation.client for simulation in simulations]
    standing = [pybullet.saveState(physicsClientId=client) for client in clients]
    body = simulations[0].body  # every world builds the same ids
    joints, n = body.actuated_joint_indices, len(body.actuated_joint_indices)
    rounds = max(1, actions // worlds)
    targets = np.random.default_rng(0).uniform(
        -physics.action_range, physics.action_range, (rounds, worlds, n)).tolist()
    forces, position_gains, velocity_gains = ([value] * n for value in
                                              (physics.max_torque, physics.position_gain, physics.velocity_gain))
    with Stopwatch() as stopwatch:
        for step, round_targets in enumerate(targets):
            for client, state, target in zip(clients, standing, round_targets, strict=True):
                if step % episode_length == 0:
                    pybullet.restoreState(state, physicsClientId=client)
                pybullet.setJointMotorControlArray(
                    body.body_id, joints, pybullet.POSITION_CONTROL, targetPositions=target, forces=forces,
                    positionGains=position_gains, velocityGains=velocity_gains, physicsClientId=client,
                )
                for _ in range(physics.substeps):
                    pybullet.stepSimulation(physicsClientId=client)
    for simulation in simulations:
        simulation.close()
    return stopwatch.result(rounds * worlds)


def gymnasium_env(actions: int) -> tuple[float, float]:
    env = WalkerEnv(DE)
    env.reset(seed=0)
    env.reset()  # the second reset saves the standing state that later resets restore
    samples = np.random.default_rng(0).uniform(-1, 1, (actions, 4))
    with Stopwatch() as stopwatch:
        for action in samples:
            if env.step(action)[3]:
                env.reset()
    env.close()
    return stopwatch.result(actions)


class ReplayedActions:
    """A rollout policy that plays actions drawn before the timer starts.

    The raw and gymnasium loops draw their random actions up front, so the TorchRL
    variants do too: every variant is timed on stepping alone, none on drawing actions
    (TorchRL's default random policy costs about 0.1-0.2 ms per step through its specs).
    """

    def __init__(self, actions: torch.Tensor):
        self.actions, self.calls = actions, 0

    def __call__(self, tensordict):
        tensordict.set("action", self.actions[self.calls])
        self.calls += 1
        return tensordict


def torchrl_env(make_env, actions: int) -> tuple[float, float]:
    env = make_env()
    env.set_seed(0)
    steps = max(1, actions // env.batch_size.numel())
    generator = torch.Generator().manual_seed(0)
    policy = ReplayedActions(torch.rand((steps, *env.action_spec.shape), generator=generator) * 2 - 1)
    # Warm-up, untimed: worker start and two resets. A DE robot's second reset rebuilds it
    # once more and saves that state (WalkerSimulation.reset); from then on every reset
    # restores it, as the raw loop does. With one warm-up reset, the timed rollout's own
    # reset paid for 32 robot builds per worker, which the raw loop never does.
    for _ in range(2):
        env.rollout(2, break_when_any_done=False)
    with Stopwatch() as stopwatch:
        env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    return stopwatch.result(steps * env.batch_size.numel())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--actions", type=int, default=3000, help="actions per variant and repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)

    variants = {
        "raw PyBullet loop": raw_pybullet,
        "raw PyBullet loop, 32 worlds in turn": functools.partial(raw_pybullet, worlds=32),
        "WalkerEnv (gymnasium)": gymnasium_env,
        **{
            f"BatchedWalkerEnv N={n}": functools.partial(torchrl_env, functools.partial(BatchedWalkerEnv, n, DE))
            for n in (1, 8, 32)
        },
        **{
            f"{cls.__name__} 2 workers x N={n}": functools.partial(
                torchrl_env,
                functools.partial(cls, 2, functools.partial(BatchedWalkerEnv, n, DE), mp_start_method="fork"),
            )
            for cls, n in ((ParallelEnv, 16), (SleepingParallelEnv, 16), (SleepingParallelEnv, 32))
        },
    }
    results = {name: [] for name in variants}
    for _ in range(args.repeats):  # interleave repeats so drift in machine load hits every variant
        for name, run in variants.items():
            results[name].append(run(args.actions))
    rates = {name: [rate for rate, _ in values] for name, values in results.items()}
    cpu_shares = {name: statistics.median(share for _, share in values) for name, values in results.items()}
    raw = statistics.median(rates["raw PyBullet loop"])
    print(f"{'variant':40s} {'actions/s':>10s} {'x raw':>7s} {'CPU of this process':>20s}")
    for name, values in rates.items():
        print(f"{name:40s} {statistics.median(values):10.0f} {statistics.median(values) / raw:7.3f} "
              f"{cpu_shares[name]:20.2f}")
    # The headline ratios pair each repeat's two runs, made seconds apart, and take the median
    # over repeats: a change in machine load between repeats then moves both sides of a ratio.
    print("paired ratios, median (min-max) over repeats:")
    single = rates["BatchedWalkerEnv N=32"]
    for name in rates:
        if "2 workers" in name:
            print(f"{name} / BatchedWalkerEnv N=32 (2 cores / 1 core): {paired(rates[name], single)}")
    print(f"BatchedWalkerEnv N=32 / raw PyBullet loop: {paired(single, rates['raw PyBullet loop'])}")
    print("BatchedWalkerEnv N=32 / raw loop over 32 worlds (what the env adds to the physics): "
          f"{paired(single, rates['raw PyBullet loop, 32 worlds in turn'])}")
    print(f"env_throughput_ratio: {statistics.median(paired_ratios(single, rates['raw PyBullet loop'])):.3f}")


def paired_ratios(numerators: list[float], denominators: list[float]) -> list[float]:
    return [top / bottom for top, bottom in zip(numerators, denominators, strict=True)]


def paired(numerators: list[float], denominators: list[float]) -> str:
    ratios = paired_ratios(numerators, denominators)
    return f"{statistics.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})"


if __name__ == "__main__":
    main()
