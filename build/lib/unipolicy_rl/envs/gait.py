"""An open-loop sinusoidal gait: shows the robot can walk before any learning.

    python -m unipolicy_rl.envs.gait                 # DE robot, prints metres walked
    python -m unipolicy_rl.envs.gait --gif walk.gif  # and records the episode

:class:`RandomPhaseGait` is the same idea for any batch of robots, as a TorchRL policy with a
random phase per robot and joint and noise on top: data that moves every body, of any
morphology, before any policy is trained (a world model's accuracy is measured on it).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase

from unipolicy_rl.envs.design import Design, DesignDistribution
from unipolicy_rl.envs.walker import WalkerEnv


@dataclass(frozen=True)
class SineGait:
    """Each actuated joint follows ``amplitude * sin(2 pi frequency t + phase)`` (action units).

    The defaults came from a random search over amplitude, frequency and the four phases
    on the DE robot, scoring forward minus twice sideways displacement.
    """

    amplitude: float = 0.57
    frequency: float = 1.7  # Hz
    phases: tuple[float, ...] = (0.0, 2.04, 4.94, 0.34)  # FL, FR, RL, RR hips

    def action(self, step: int, control_period: float) -> np.ndarray:
        time = step * control_period
        return self.amplitude * np.sin(2 * np.pi * self.frequency * time + np.asarray(self.phases))


class RandomPhaseGait:
    """A TorchRL policy for a batched env with actions ``[robots, slots]`` in [-1, 1]: slot ``j`` of
    robot ``i`` follows ``amplitude * sin(2 pi frequency t + phase[i, j])`` plus Gaussian ``noise``,
    clipped; phases drawn once, uniform, from ``seed``. One instance per rollout (it counts the steps
    from its first call); the same seed gives the same actions."""

    def __init__(self, robots: int, slots: int, control_period: float, amplitude: float = 0.6,
                 frequency: float = 1.5, noise: float = 0.2, seed: int = 0) -> None:
        self.generator = torch.Generator().manual_seed(seed)
        self.phase = torch.rand(robots, slots, generator=self.generator) * 2 * np.pi
        self.control_period, self.amplitude, self.frequency, self.noise = control_period, amplitude, frequency, noise
        self.step = 0

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        time = self.step * self.control_period
        wave = self.amplitude * torch.sin(2 * np.pi * self.frequency * time + self.phase)
        tensordict.set("action", (wave + self.noise * torch.randn(wave.shape, generator=self.generator)).clamp(-1, 1))
        self.step += 1
        return tensordict


def walk(env: WalkerEnv, gait: SineGait, design: Design | None = None, frames: list | None = None) -> dict:
    """Runs one episode of ``gait``; returns the final ``info`` with the episode's total reward."""
    env.reset(seed=0, options={"design": design} if design else None)
    total, info, step = 0.0, {}, 0
    truncated = False
    while not truncated:
        _, reward, _, truncated, info = env.step(gait.action(step, env.simulation.physics.control_period))
        total += reward
        step += 1
        if frames is not None:
            frames.append(env.render())
    return {**info, "episode_reward": total, "steps": step}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--length", type=float, default=0.175, help="link length l (m)")
    parser.add_argument("--density", type=float, default=0.5, help="link density rho (kg/m)")
    parser.add_argument("--gif", help="write the episode as an animated GIF to this path")
    args = parser.parse_args(argv)
    env = WalkerEnv(DesignDistribution.fixed(args.length, args.density), render_mode="rgb_array" if args.gif else None)
    frames = [] if args.gif else None
    result = walk(env, SineGait(), frames=frames)
    env.close()
    print(
        f"design l={args.length} rho={args.density}: walked {result['forward_displacement']:.2f} m forward "
        f"in {result['steps']} actions ({result['mean_forward_speed']:.3f} m/s), "
        f"episode reward {result['episode_reward']:.1f}"
    )
    if args.gif:
        from PIL import Image

        images = [Image.fromarray(frame) for frame in frames]
        images[0].save(args.gif, save_all=True, append_images=images[1:], duration=1000 // 15, loop=0)
        print(f"wrote {args.gif}")
    return result


if __name__ == "__main__":
    main()
