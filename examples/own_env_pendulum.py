"""Bringing your own env: ME-TRPO on gymnasium's Pendulum-v1 from the library's parts.

    python examples/own_env_pendulum.py --quick            # seconds: 2 tiny epochs, both rewards
    python examples/own_env_pendulum.py --reward known     # 20 epochs of 1,000 real steps (minutes)
    python examples/own_env_pendulum.py --reward learned

Any TorchRL env with a flat continuous observation and a bounded continuous action will do:
``FlatLayout.from_env(env)`` reads the model's state and the action's bounds off its specs. The
world model needs the task's reward: a known one (a TensorDict module of the real env's keys,
here Pendulum's exact reward) or one the ensemble learns beside the state (``learn=["reward"]``,
``reward="learned"``). A task that ends early gives its termination the same way
(``termination=known_termination("Hopper-v5")``, or ``"learned"``). ``InitTracker`` marks where
episodes begin, so the replay buffer reads the starts instead of assuming them.

Each epoch: real steps with the current policy, the ensemble fitted on all of them, then TRPO
updates on imagined branches from real states until ME-TRPO's rule says stop (fewer than 70% of
the members still see the policy improve), and the deterministic policy's return on the real env.
"""

from __future__ import annotations

import argparse

import torch
from torchrl.envs import GymEnv, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.collectors import HorizonSchedule, Imagination, ImaginationSettings, StoppingRule, TransitionBuffer
from unipolicy_rl.envs.gym_functions import pendulum_reward
from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater
from unipolicy_rl.seeding import MODEL_FIT, reseed
from unipolicy_rl.world_models import LEARNED, FlatLayout, GaussianEnsemble, ModelTrainer

EPISODE_LENGTH = 200  # Pendulum-v1's time limit


def evaluate(env, actor, episodes: int) -> float:
    """The deterministic policy's mean return over ``episodes`` real episodes."""
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        returns = [env.rollout(EPISODE_LENGTH, actor)["next", "reward"].sum().item() for _ in range(episodes)]
    return sum(returns) / episodes


def main(reward: str = "known", epochs: int = 20, steps_per_epoch: int = 1000, quick: bool = False,
         seed: int = 0) -> list[tuple[int, float]]:
    """ME-TRPO on Pendulum-v1 with the ``known`` or the ``learned`` reward; returns each epoch's
    (real env steps so far, evaluation return)."""
    torch.manual_seed(seed)
    torch.set_num_threads(1)
    env = TransformedEnv(GymEnv("Pendulum-v1"), InitTracker())  # is_init: where each episode begins
    env.set_seed(seed)
    layout = FlatLayout.from_env(env)  # 3 numbers of state, one torque in [-2, 2]
    actor, critic = make_actor(layout.robot_size, 1), make_critic(layout.robot_size)
    loss = TRPOLoss(actor, critic)
    loss.make_value_estimator(gamma=0.99, lmbda=0.95)
    updater = TRPOUpdater(loss)
    # Pendulum's dynamics are smooth and 3 numbers wide: a small ensemble and short fits suffice.
    model = GaussianEnsemble(layout, action_dim=1, members=5, elites=3, hidden=(32, 32) if quick else (128, 128),
                             learn=["reward"] if reward == LEARNED else [])
    buffer = TransitionBuffer.for_model(100_000, model)
    trainer = ModelTrainer(max_epochs=2 if quick else 50, max_steps=20 if quick else 500, check_every=50,
                           validation_rows=2000)
    settings = ImaginationSettings(
        steps_per_batch=400 if quick else 2000,
        horizon=HorizonSchedule(start=10, end=25, first_epoch=2, last_epoch=10),
        stopping=StoppingRule(max_updates=2 if quick else 10, check_starts=10 if quick else 50),
    )
    known = LEARNED if reward == LEARNED else pendulum_reward()
    imagination = Imagination(model, env, known, settings, seed=seed, episode_length=EPISODE_LENGTH)
    history = []
    for epoch in range(1, epochs + 1):
        # ---- Real data
        with torch.no_grad():
            batch = env.rollout(steps_per_epoch, actor, break_when_any_done=False)
        buffer.extend(batch, epoch)
        # ---- Model training
        fit = trainer.fit(model, buffer.contents(), reseed(seed, epoch, MODEL_FIT))
        # ---- Policy training on imagined branches, until ME-TRPO's rule says stop
        imagined = imagination.epoch(epoch, buffer.contents(), actor)
        for rollout in imagined:
            updater.update(rollout)
        # ---- Evaluation on the real env
        history.append((epoch * steps_per_epoch, evaluate(env, actor, 1 if quick else 3)))
        error, updates = fit.as_metrics()["model/validation_mse"], imagined.metrics()["model/policy_updates"]
        print(f"epoch {epoch}: {reward} reward, real steps {history[-1][0]}, return {history[-1][1]:.1f}, "
              f"model error {error:.3f}, {updates:.0f} imagined updates", flush=True)
    env.close()
    return history


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reward", choices=("known", LEARNED, "both"), default="both")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--steps-per-epoch", type=int, default=1000, help="real env steps per epoch")
    parser.add_argument("--quick", action="store_true", help="2 tiny epochs (seconds): the loop runs")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    epochs, steps = (2, 200) if args.quick else (args.epochs, args.steps_per_epoch)
    for choice in ("known", LEARNED) if args.reward == "both" else (args.reward,):
        main(choice, epochs, steps, args.quick, args.seed)
