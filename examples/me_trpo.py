"""ME-TRPO from the parts, without Hydra: real episodes, a replay buffer, a world model fitted on
it, and TRPO updates on imagined branches until ME-TRPO's rule says stop.

    python examples/me_trpo.py                  # 5 epochs of 10 episodes
    python examples/me_trpo.py --epochs 2 --robots 4 --episode-length 20
    python examples/me_trpo.py --quick          # 2 epochs of 2 robots x 10 steps: does it run here?

What train.py runs for ``source=moe``, cut to its algorithm: no checkpoints, logging or
evaluation. Each part is the library's own: TorchRL's env and world-model env, our ensemble and
its trainer, the imagination with its stopping rule, and ``TRPOLoss`` with its update.
"""

from __future__ import annotations

import argparse

import torch

from unipolicy_rl.collectors import Imagination, ImaginationSettings, StoppingRule, TransitionBuffer
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights, RobotSettings
from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater
from unipolicy_rl.seeding import MODEL_FIT, reseed
from unipolicy_rl.world_models import GaussianEnsemble, ModelTrainer, StateLayout


def main(epochs: int = 5, robots: int = 10, episode_length: int = 100, seed: int = 0) -> list[float]:
    torch.manual_seed(seed)
    torch.set_num_threads(1)
    actor, critic = make_actor(18, 4), make_critic(18)
    loss = TRPOLoss(actor, critic)
    loss.make_value_estimator(gamma=0.99, lmbda=0.95)
    updater = TRPOUpdater(loss)
    env = BatchedWalkerEnv(robots, full_state=True, episode_length=episode_length)  # "state": every link, for the model
    layout = StateLayout.for_env(RobotSettings(), observation="thesis", append_design=False, model_state="full")
    model = GaussianEnsemble(layout, action_dim=4)
    buffer = TransitionBuffer.for_model(200_000, model)
    settings = ImaginationSettings(steps_per_batch=2000, stopping=StoppingRule(max_updates=10, check_starts=20))
    imagination = Imagination(model, env, RewardWeights(), settings, seed=seed, episode_length=episode_length)
    returns = []
    for epoch in range(1, epochs + 1):
        # ---- Real data
        with torch.no_grad():
            batch = env.rollout(episode_length, actor, break_when_any_done=False)
        returns.append(batch["next", "reward"].sum(-2).mean().item())
        # ---- Model training
        buffer.extend(batch, epoch)
        fit = ModelTrainer(max_epochs=10).fit(model, buffer.contents(), reseed(seed, epoch, MODEL_FIT))
        # ---- Policy training on imagined branches, until ME-TRPO's rule says stop
        imagined = imagination.epoch(epoch, buffer.contents(), actor)
        for rollout in imagined:
            updater.update(rollout)
        error, updates = fit.as_metrics()["model/validation_mse"], imagined.metrics()["model/policy_updates"]
        print(f"epoch {epoch}: real return {returns[-1]:.2f}, model error {error:.3f}, {updates:.0f} imagined updates")
    env.close()
    return returns


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--robots", type=int, default=10, help="real episodes per epoch")
    parser.add_argument("--episode-length", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="2 epochs of 2 robots x 10 steps: a check that it runs")
    args = parser.parse_args()
    if args.quick:
        args.epochs, args.robots, args.episode_length = 2, 2, 10
    main(args.epochs, args.robots, args.episode_length, args.seed)
