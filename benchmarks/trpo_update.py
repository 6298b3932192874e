"""Time one full TRPO update: ours (TorchRL TRPOLoss + TRPOUpdater) against sb3-contrib's TRPO.

Both sides get the same work on the same batch size: a 64x64 tanh Gaussian policy and a
separate 64x64 tanh critic, observation dim 18, action dim 4; a batch of ``--samples``
transitions (episodes of 100 steps); 10 conjugate-gradient iterations, damping 0.1,
max KL 0.01, backtracking line search (factor 0.8, up to 10 tries); critic Adam (lr 1e-3)
for 10 epochs of minibatches of 128. One thread each (``torch.set_num_threads(1)``).

Both take the exact Hessian of the mean KL at the current policy as the Fisher matrix; SB3
gets each product by double backward through the network, ours by the chain rule
``J^T M J v`` (see ``unipolicy_rl/objectives/natural_gradient.py``), the same numbers for
less work. Ours also uses a hand-written backward pass for the MLP critic and calls Adam's
functional kernel (both checked against autograd / ``Optimizer.step`` in the tests).

SB3: ``TRPO.train()`` on a rollout buffer filled with random observations and actions drawn
from its own policy (so the importance ratio starts at 1, as after a real rollout), with
returns and advantages already computed (SB3 computes them during collection).
Ours: ``TRPOUpdater.update(batch)`` on a TensorDict batch of the same size, built the same
way; our timing *includes* computing GAE (critic forward on observations and next
observations), which SB3 does outside ``train()``.

Each side: one warm-up update, then ``--repeats`` timed updates on fresh batches, the two
alternating repetition by repetition so that load from other processes hits both alike. The
medians (wall clock, and process CPU time) and their ratio are printed, the last line being
``trpo_update_ratio: <ours/sb3>`` (wall clock).

Run from the repository root::

    python benchmarks/trpo_update.py            # 16,000 samples, 5 repeats
    python benchmarks/trpo_update.py --samples 2000 --repeats 3   # quick check
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater

OBSERVATION_DIM = 18
ACTION_DIM = 4
EPISODE_LENGTH = 100
SETTINGS = {
    "hidden_sizes": (64, 64),
    "activation": "tanh",
    "cg_iters": 10,
    "damping": 0.1,
    "max_kl": 0.01,
    "backtrack_factor": 0.8,
    "max_backtracks": 10,
    "critic_epochs": 10,
    "critic_minibatch_size": 128,
    "critic_lr": 1e-3,
    "gamma": 0.99,
    "gae_lambda": 0.95,
}


# ----------------------------------------------------------------------------------------- ours
def make_our_batch(actor, samples: int, generator: torch.Generator) -> TensorDict:
    """Random observations, actions sampled from ``actor``, episodes of EPISODE_LENGTH steps."""
    envs = max(samples // 1000, 1)
    steps = samples // envs
    observation = torch.randn(envs, steps, OBSERVATION_DIM, generator=generator)
    batch = TensorDict(observation=observation, batch_size=[envs, steps])
    with torch.no_grad():
        actor(batch)
    done = torch.zeros(envs, steps, 1, dtype=torch.bool)
    done[:, EPISODE_LENGTH - 1 :: EPISODE_LENGTH] = True
    batch["next"] = TensorDict(
        observation=torch.randn(envs, steps, OBSERVATION_DIM, generator=generator),
        reward=torch.randn(envs, steps, 1, generator=generator),
        done=done,
        terminated=done.clone(),
        batch_size=[envs, steps],
    )
    return batch


class OurUpdate:
    """Our TRPOUpdater on fresh TensorDict batches; ``run()`` times one update."""

    name = "ours"

    def __init__(self, samples: int) -> None:
        torch.manual_seed(0)
        self.samples = samples
        self.generator = torch.Generator().manual_seed(0)
        self.actor = make_actor(OBSERVATION_DIM, ACTION_DIM, SETTINGS["hidden_sizes"], SETTINGS["activation"])
        critic = make_critic(OBSERVATION_DIM, SETTINGS["hidden_sizes"], SETTINGS["activation"])
        loss = TRPOLoss(self.actor, critic)
        loss.make_value_estimator(gamma=SETTINGS["gamma"], lmbda=SETTINGS["gae_lambda"])
        self.updater = TRPOUpdater(
            loss,
            max_kl=SETTINGS["max_kl"],
            damping=SETTINGS["damping"],
            cg_iters=SETTINGS["cg_iters"],
            backtrack_factor=SETTINGS["backtrack_factor"],
            max_backtracks=SETTINGS["max_backtracks"],
            critic_lr=SETTINGS["critic_lr"],
            critic_epochs=SETTINGS["critic_epochs"],
            critic_minibatch_size=SETTINGS["critic_minibatch_size"],
            generator=self.generator,
        )

    def run(self) -> tuple[float, float, str]:
        batch = make_our_batch(self.actor, self.samples, self.generator)
        wall, cpu = time.perf_counter(), time.process_time()
        metrics = self.updater.update(batch)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        note = (
            f"accepted={metrics['train/step_accepted']:.0f}"
            f" tries={metrics['train/line_search_tries']:.0f} kl={metrics['train/kl']:.4f}"
        )
        return wall, cpu, note


# ----------------------------------------------------------------------------------------- SB3
class _BoxEnv(gym.Env):
    """A do-nothing env with the walker's spaces; SB3 only needs it for shapes."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (OBSERVATION_DIM,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(OBSERVATION_DIM, np.float32), {}

    def step(self, action):
        return np.zeros(OBSERVATION_DIM, np.float32), 0.0, False, False, {}


def fill_sb3_buffer(model, samples: int, rng: np.random.Generator) -> None:
    """Fill the rollout buffer as a rollout of ``samples`` steps would, without an env."""
    buffer = model.rollout_buffer
    buffer.reset()
    observations = rng.standard_normal((samples, 1, OBSERVATION_DIM)).astype(np.float32)
    with torch.no_grad():
        actions, values, log_probs = model.policy(torch.as_tensor(observations[:, 0]))
    buffer.observations[:] = observations
    buffer.actions[:] = actions.numpy()[:, None]
    buffer.values[:] = values.numpy()
    buffer.log_probs[:] = log_probs.numpy()[:, None]
    buffer.rewards[:] = rng.standard_normal((samples, 1)).astype(np.float32)
    buffer.episode_starts[:] = 0.0
    buffer.episode_starts[::EPISODE_LENGTH] = 1.0
    buffer.pos = samples
    buffer.full = True
    buffer.compute_returns_and_advantage(last_values=torch.zeros(1), dones=np.ones(1))


class SB3Update:
    """sb3-contrib's TRPO on a freshly filled rollout buffer; ``run()`` times ``train()``."""

    name = "sb3"

    def __init__(self, samples: int) -> None:
        from sb3_contrib import TRPO
        from stable_baselines3.common.logger import Logger

        self.samples = samples
        self.model = TRPO(
            "MlpPolicy",
            _BoxEnv(),
            learning_rate=SETTINGS["critic_lr"],
            n_steps=samples,
            batch_size=SETTINGS["critic_minibatch_size"],
            gamma=SETTINGS["gamma"],
            gae_lambda=SETTINGS["gae_lambda"],
            cg_max_steps=SETTINGS["cg_iters"],
            cg_damping=SETTINGS["damping"],
            line_search_shrinking_factor=SETTINGS["backtrack_factor"],
            line_search_max_iter=SETTINGS["max_backtracks"],
            n_critic_updates=SETTINGS["critic_epochs"],
            target_kl=SETTINGS["max_kl"],
            policy_kwargs={
                "net_arch": {
                    "pi": list(SETTINGS["hidden_sizes"]),
                    "vf": list(SETTINGS["hidden_sizes"]),
                },
                "activation_fn": torch.nn.Tanh,
            },
            device="cpu",
            seed=0,
        )
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        self.rng = np.random.default_rng(0)

    def run(self) -> tuple[float, float, str]:
        fill_sb3_buffer(self.model, self.samples, self.rng)
        wall, cpu = time.perf_counter(), time.process_time()
        self.model.train()
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        success = self.model.logger.name_to_value.get("train/is_line_search_success", float("nan"))
        return wall, cpu, f"accepted={success:.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=16_000, help="transitions per batch")
    parser.add_argument("--repeats", type=int, default=5, help="timed updates after a warm-up")
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", category=UserWarning)

    print(f"batch: {args.samples} samples, obs {OBSERVATION_DIM}, action {ACTION_DIM}")
    print("settings (both): " + ", ".join(f"{k}={v}" for k, v in SETTINGS.items()))
    contenders = [SB3Update(args.samples), OurUpdate(args.samples)]
    wall: dict[str, list[float]] = {c.name: [] for c in contenders}
    cpu: dict[str, list[float]] = {c.name: [] for c in contenders}
    # Alternate the two, so load from other processes on a shared machine hits both alike.
    for repeat in range(args.repeats + 1):
        for contender in contenders:
            elapsed, cpu_elapsed, note = contender.run()
            label = "warm-up" if repeat == 0 else f"rep {repeat}"
            print(f"  {contender.name:4s} {label:7s}: {elapsed:.3f} s wall, {cpu_elapsed:.3f} s cpu  {note}")
            if repeat > 0:
                wall[contender.name].append(elapsed)
                cpu[contender.name].append(cpu_elapsed)
    median_wall = {name: statistics.median(times) for name, times in wall.items()}
    median_cpu = {name: statistics.median(times) for name, times in cpu.items()}
    print(f"sb3-contrib TRPO.train() median: {median_wall['sb3']:.3f} s wall, {median_cpu['sb3']:.3f} s cpu")
    print(f"unipolicy_rl TRPOUpdater.update() median: {median_wall['ours']:.3f} s wall, {median_cpu['ours']:.3f} s cpu")
    print(f"cpu-time ratio (ours/sb3): {median_cpu['ours'] / median_cpu['sb3']:.3f}")
    print(f"trpo_update_ratio: {median_wall['ours'] / median_wall['sb3']:.3f}")


if __name__ == "__main__":
    main()
