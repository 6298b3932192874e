"""MBPO from the parts, without Hydra: real episodes, a world model fitted on them, short model
branches from real states, and TorchRL's ``SACLoss`` trained mostly on the model's branches.

    python examples/mbpo.py                  # 5 epochs of 10 episodes, 1 gradient step per real step
    python examples/mbpo.py --epochs 2 --robots 4 --episode-length 20
    python examples/mbpo.py --quick          # 2 epochs of 2 robots x 10 steps: does it run here?

What train.py runs for ``source=moe algo=sac imagination=mbpo``, cut to its algorithm: no
observation normaliser, checkpoints, logging or evaluation. The world model, its trainer and
the imagination are the library's; the loss, its target-network updater and both replay
buffers are TorchRL's.
"""

from __future__ import annotations

import argparse

import torch
from torchrl.data import Bounded, LazyTensorStorage, ReplayBuffer
from torchrl.objectives import SACLoss, SoftUpdate

from unipolicy_rl.collectors import HorizonSchedule, Imagination, ImaginationSettings, StoppingRule, TransitionBuffer
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights, RobotSettings
from unipolicy_rl.networks import make_q_network, make_tanh_actor
from unipolicy_rl.seeding import MODEL_FIT, reseed
from unipolicy_rl.world_models import GaussianEnsemble, ModelTrainer, StateLayout

KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "terminated"))


def main(epochs: int = 5, robots: int = 10, episode_length: int = 100, updates_per_step: int = 1,
         real_data_share: float = 0.05, batch_size: int = 256, seed: int = 0) -> list[float]:
    torch.manual_seed(seed)
    torch.set_num_threads(1)
    actor = make_tanh_actor(18, 4)
    loss = SACLoss(actor, make_q_network(18, 4), num_qvalue_nets=2, delay_qvalue=True,
                   action_spec=Bounded(-1.0, 1.0, shape=(4,)))
    loss.make_value_estimator(gamma=0.99)
    optimizer = torch.optim.Adam(loss.parameters(), lr=3e-4)
    target_update = SoftUpdate(loss, tau=0.005)
    real_data = ReplayBuffer(storage=LazyTensorStorage(100_000))
    model_data = ReplayBuffer(storage=LazyTensorStorage(50_000))  # the latest fits' branches
    env = BatchedWalkerEnv(robots, full_state=True, episode_length=episode_length)  # "state": every link, for the model
    layout = StateLayout.for_env(RobotSettings(), observation="thesis", append_design=False, model_state="full")
    model = GaussianEnsemble(layout, action_dim=4)
    transitions = TransitionBuffer.for_model(200_000, model)
    settings = ImaginationSettings(steps_per_batch=2000, member_per_step=True, train_on_real=True,
                                   horizon=HorizonSchedule(start=1, end=5, first_epoch=1, last_epoch=epochs),
                                   stopping=StoppingRule(kind="fixed", max_updates=1))
    imagination = Imagination(model, env, RewardWeights(), settings, seed=seed, episode_length=episode_length)
    returns = []
    for epoch in range(1, epochs + 1):
        # ---- Real data: the real buffer, and the model's training data
        with torch.no_grad():
            batch = env.rollout(episode_length, actor, break_when_any_done=False)
        returns.append(batch["next", "reward"].sum(-2).mean().item())
        real_data.extend(batch.reshape(-1).select(*KEYS))
        transitions.extend(batch, epoch)
        fit = ModelTrainer(max_epochs=10).fit(model, transitions.contents(), reseed(seed, epoch, MODEL_FIT))
        # ---- Model data: one batch of short branches from real states
        for branches in imagination.epoch(epoch, transitions.contents(), actor):
            model_data.extend(branches.reshape(-1).select(*KEYS))
        # ---- SAC steps on minibatches mostly of model data
        real = round(batch_size * real_data_share)
        for _ in range(updates_per_step * batch.numel()):
            minibatch = torch.cat([real_data.sample(real), model_data.sample(batch_size - real)])
            losses = loss(minibatch)
            optimizer.zero_grad()
            (losses["loss_qvalue"] + losses["loss_actor"] + losses["loss_alpha"]).backward()
            optimizer.step()
            target_update.step()
        error = fit.as_metrics()["model/validation_mse"]
        print(f"epoch {epoch}: real return {returns[-1]:.2f}, model error {error:.3f}, "
              f"{len(model_data)} model transitions, critic loss {losses['loss_qvalue'].item():.3f}")
    env.close()
    return returns


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--robots", type=int, default=10, help="real episodes per epoch")
    parser.add_argument("--episode-length", type=int, default=100)
    parser.add_argument("--updates-per-step", type=int, default=1, help="SAC steps per real step (MBPO: 20)")
    parser.add_argument("--real-data-share", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="2 epochs of 2 robots x 10 steps: a check that it runs")
    args = parser.parse_args()
    if args.quick:
        args.epochs, args.robots, args.episode_length = 2, 2, 10
    main(args.epochs, args.robots, args.episode_length, args.updates_per_step, args.real_data_share, seed=args.seed)
