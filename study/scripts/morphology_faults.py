"""Which of the split's robots the simulator runs: physics faults per morphology under random actions.

    python study/scripts/morphology_faults.py [--side train|held_out] [--count 8] [--robots 8] [--steps 100] [--seed 0]
        [Hydra overrides of the grammar config, e.g. robot.physics.max_joint_speed=null]

A robot that stands (the split's filter) can still blow up once driven: a light distal link
flailing under its motor's torque reaches tens of m/s, the observation passes the explosion
limit (``unipolicy_rl.envs.limits.EXPLOSION_LIMIT``) and the env ends the episode as a
physics fault. A policy cannot learn where most episodes end so (a specialist on such a robot
faulted in every episode and learned nothing, docs/grammar.md), so this measures it before any
training: the first ``--count`` morphologies of ``--side`` (the ones a study's specialists use),
each as ``--robots`` robots of random designs driven by uniform random actions for ``--steps``
steps (robots that fault start a new episode), and prints per morphology the faults per 1,000
robot-steps, over the steps just before each fault the largest link speed (m/s) and link
rotation rate (rad/s) reached, and the farthest any robot's base got from its start (m) and the
highest it got: a change that stops the faults by flinging robots about (a clamp on the joints'
state does: docs/grammar.md) shows there.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from unipolicy_rl.env_factories import make_morphology_env

CONF = Path(__file__).resolve().parents[1] / "conf"
LINK_STATE = 13  # per link: position 3, orientation quaternion 4, linear velocity 3, angular velocity 3


def link_speeds(values: list[float]) -> tuple[float, float]:
    """The largest link speed and rotation rate in one robot's world state."""
    state = np.asarray(values).reshape(-1, LINK_STATE)
    return float(np.linalg.norm(state[:, 7:10], axis=1).max()), float(np.linalg.norm(state[:, 10:13], axis=1).max())


def fault_rate(side: str, index: int, robots: int, steps: int, seed: int,
               overrides: tuple[str, ...] = ()) -> dict[str, float]:
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["robot=grammar", f"robot.morphologies={side}", f"robot.specialist={index}",
                                           *overrides])
    torch.manual_seed(seed)
    env = make_morphology_env(cfg, robots)
    try:
        env.set_seed(seed)
        td = env.reset()
        before = [sim.read()[0] for sim in env.simulations]
        faults, speeds, rates, travel, height = 0, [], [], 0.0, 0.0
        for _ in range(steps):
            td["action"] = env.action_spec.rand()
            out = env.step(td)["next"]
            for robot in out["physics_fault"].reshape(-1).nonzero().flatten().tolist():
                faults += 1
                speed, rate = link_speeds(before[robot])
                speeds.append(speed)
                rates.append(rate)
            before = [sim.read()[0] for sim in env.simulations]
            bases = np.asarray([values[:3] for values in before])  # each robot starts at the origin
            travel = max(travel, float(np.linalg.norm(bases[:, :2], axis=1).max()))
            height = max(height, float(bases[:, 2].max()))
            td = env.reset(out.clone()) if out["done"].any() else out.clone()
    finally:
        env.close()
    return {"faults_per_1000": 1000.0 * faults / (robots * steps),
            "speed_before_fault": max(speeds, default=float("nan")),
            "rate_before_fault": max(rates, default=float("nan")), "farthest": travel, "highest": height}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--side", choices=("train", "held_out"), default=None,
                        help="one side of the split (default: both)")
    parser.add_argument("--count", type=int, default=8, help="the first this many morphologies of each side")
    parser.add_argument("--robots", type=int, default=8, help="robots per morphology, each of a random design")
    parser.add_argument("--steps", type=int, default=100, help="random actions per robot")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the grammar config")
    args = parser.parse_args(argv)
    for name in ("count", "robots", "steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    sides = (args.side,) if args.side else ("train", "held_out")
    print("| side | morphology | faults per 1,000 robot-steps | largest link speed before a fault (m/s) "
          "| largest link rotation rate before a fault (rad/s) | farthest base from its start (m) | highest base (m) |")
    print("|---|---|---|---|---|---|---|")
    faulty = 0
    for side in sides:
        for index in range(args.count):
            result = fault_rate(side, index, args.robots, args.steps, args.seed, tuple(args.overrides))
            faulty += result["faults_per_1000"] > 0
            print(f"| {side} | {index} | {result['faults_per_1000']:.1f} | {result['speed_before_fault']:.1f} "
                  f"| {result['rate_before_fault']:.1f} | {result['farthest']:.1f} | {result['highest']:.2f} |",
                  flush=True)
    print(f"{faulty} of {len(sides) * args.count} morphologies faulted under random actions")
    return 0


if __name__ == "__main__":
    sys.exit(main())
