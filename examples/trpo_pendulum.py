"""TRPO on a standard TorchRL env: gymnasium's Pendulum through TorchRL's ``GymEnv``, no robot.

    python examples/trpo_pendulum.py            # 30 updates of 8 episodes (a few minutes)
    python examples/trpo_pendulum.py --quick    # 2 small updates, to check it runs (seconds)

The library's ``TRPOLoss`` (a TorchRL ``LossModule``) and ``TRPOUpdater`` (the natural-gradient
step, then the critic fit) work on any TorchRL env whose actions are continuous: the actor and
critic come from ``unipolicy_rl.networks``, the batches from TorchRL's ``Collector``.
"""

from __future__ import annotations

import argparse

import torch
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, StepCounter, TransformedEnv

from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater


def main(updates: int = 30, episodes_per_update: int = 8, episode_length: int = 200, seed: int = 0) -> list[float]:
    torch.manual_seed(seed)
    env = TransformedEnv(GymEnv("Pendulum-v1"), StepCounter(max_steps=episode_length))
    env.set_seed(seed)
    observation_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    actor = make_actor(observation_dim, action_dim, action_spec=env.action_spec)
    loss = TRPOLoss(actor, make_critic(observation_dim))
    loss.make_value_estimator(gamma=0.99, lmbda=0.95)
    updater = TRPOUpdater(loss)
    collector = Collector(
        env,
        actor,
        frames_per_batch=episodes_per_update * episode_length,
        total_frames=updates * episodes_per_update * episode_length,
        auto_register_policy_transforms=False,  # the actor needs no transform of the env
    )
    returns = []
    for update, batch in enumerate(collector, start=1):
        # One batch: [frames], time last; the done flags split it into episodes for GAE.
        returns.append(batch["next", "reward"].sum().item() / episodes_per_update)
        metrics = updater.update(batch)
        print(f"update {update}: episode return {returns[-1]:.1f}, KL {metrics['train/kl']:.4f}")
    collector.shutdown()
    return returns


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, default=30)
    parser.add_argument("--episodes", type=int, default=8, help="episodes per update")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="2 updates of 2 short episodes")
    args = parser.parse_args()
    if args.quick:
        main(updates=2, episodes_per_update=2, episode_length=50, seed=args.seed)
    else:
        main(args.updates, args.episodes, seed=args.seed)
