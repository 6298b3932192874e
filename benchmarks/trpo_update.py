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
    python benchmarks/trpo_update.py --samples 5000 --fisher-fraction 0.2   # and ours on a fifth
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
import warnings
from collections.abc import Callable
from typing import TypeVar

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater, TrustRegion
from unipolicy_rl.training.metrics_file import KL, LINE_SEARCH_TRIES, STEP_ACCEPTED

T = TypeVar("T")

OBSERVATION_DIM = 18
ACTION_DIM = 4
EPISODE_LENGTH = 100
NETWORK = {"hidden_sizes": (64, 64), "activation": "tanh"}
TRUST_REGION = TrustRegion(max_kl=0.01, damping=0.1, cg_iters=10, backtrack_factor=0.8, max_backtracks=10)
UPDATE = {
    "critic_epochs": 10,
    "critic_minibatch_size": 128,
    "critic_lr": 1e-3,
}
RETURNS = {"gamma": 0.99, "gae_lambda": 0.95}
SETTINGS = {**NETWORK, **dataclasses.asdict(TRUST_REGION), **UPDATE, **RETURNS}
TORCH_ACTIVATIONS = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}


def random_rollout(envs: int, steps: int, generator: torch.Generator) -> TensorDict:
    """Random observations, next observations and rewards shaped ``[envs, steps]``.

    An episode ends every EPISODE_LENGTH steps. Actions are left out: each side samples them
    from its own policy, so the importance ratio starts at 1, as after a real rollout.
    """
    done = torch.zeros(envs, steps, 1, dtype=torch.bool)
    done[:, EPISODE_LENGTH - 1 :: EPISODE_LENGTH] = True
    return TensorDict(
        observation=torch.randn(envs, steps, OBSERVATION_DIM, generator=generator),
        next=TensorDict(
            observation=torch.randn(envs, steps, OBSERVATION_DIM, generator=generator),
            reward=torch.randn(envs, steps, 1, generator=generator),
            done=done,
            terminated=done.clone(),
            batch_size=[envs, steps],
        ),
        batch_size=[envs, steps],
    )


def timed(function: Callable[..., T], *args: object) -> tuple[float, float, T]:
    """Wall-clock and process CPU seconds of ``function(*args)``, and its result."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = function(*args)
    return time.perf_counter() - wall, time.process_time() - cpu, result


# ----------------------------------------------------------------------------------------- ours
class OurUpdate:
    """Our TRPOUpdater on fresh TensorDict batches; ``run()`` times one update."""

    def __init__(self, samples: int, fisher_fraction: float = 1.0) -> None:
        self.name = "ours" if fisher_fraction == 1.0 else f"ours, Fisher on {fisher_fraction:g}"
        torch.manual_seed(0)
        self.envs = max(samples // 1000, 1)
        self.steps = samples // self.envs
        self.generator = torch.Generator().manual_seed(0)
        self.actor = make_actor(OBSERVATION_DIM, ACTION_DIM, **NETWORK)
        loss = TRPOLoss(self.actor, make_critic(OBSERVATION_DIM, **NETWORK))
        loss.make_value_estimator(gamma=RETURNS["gamma"], lmbda=RETURNS["gae_lambda"])
        trust_region = dataclasses.replace(TRUST_REGION, fisher_fraction=fisher_fraction)
        self.updater = TRPOUpdater(loss, trust_region=trust_region, **UPDATE, generator=self.generator)

    def run(self) -> tuple[float, float, str]:
        batch = random_rollout(self.envs, self.steps, self.generator)
        with torch.no_grad():
            self.actor(batch)
        wall, cpu, metrics = timed(self.updater.update, batch)
        note = (
            f"accepted={metrics[STEP_ACCEPTED]:.0f}"
            f" tries={metrics[LINE_SEARCH_TRIES]:.0f} kl={metrics[KL]:.4f}"
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


def fill_sb3_buffer(model, rollout: TensorDict) -> None:
    """Fill the rollout buffer from a one-env ``rollout``, as collecting it would have."""
    buffer = model.rollout_buffer
    buffer.reset()
    observations = rollout["observation"][0]
    with torch.no_grad():
        actions, values, log_probs = model.policy(observations)
    buffer.observations[:] = observations[:, None].numpy()
    buffer.actions[:] = actions[:, None].numpy()
    buffer.values[:] = values.numpy()
    buffer.log_probs[:] = log_probs[:, None].numpy()
    buffer.rewards[:] = rollout["next", "reward"][0].numpy()
    buffer.episode_starts[::EPISODE_LENGTH] = 1.0
    buffer.pos = buffer.buffer_size
    buffer.full = True
    buffer.compute_returns_and_advantage(last_values=torch.zeros(1), dones=np.ones(1))


class SB3Update:
    """sb3-contrib's TRPO on a freshly filled rollout buffer; ``run()`` times ``train()``."""

    name = "sb3"

    def __init__(self, samples: int) -> None:
        from sb3_contrib import TRPO
        from stable_baselines3.common.logger import Logger

        self.samples = samples
        self.generator = torch.Generator().manual_seed(0)
        self.model = TRPO(
            "MlpPolicy",
            _BoxEnv(),
            learning_rate=UPDATE["critic_lr"],
            n_steps=samples,
            batch_size=UPDATE["critic_minibatch_size"],
            gamma=RETURNS["gamma"],
            gae_lambda=RETURNS["gae_lambda"],
            cg_max_steps=TRUST_REGION.cg_iters,
            cg_damping=TRUST_REGION.damping,
            line_search_shrinking_factor=TRUST_REGION.backtrack_factor,
            line_search_max_iter=TRUST_REGION.max_backtracks,
            n_critic_updates=UPDATE["critic_epochs"],
            target_kl=TRUST_REGION.max_kl,
            policy_kwargs={
                "net_arch": {"pi": list(NETWORK["hidden_sizes"]), "vf": list(NETWORK["hidden_sizes"])},
                "activation_fn": TORCH_ACTIVATIONS[NETWORK["activation"]],
            },
            device="cpu",
            seed=0,
        )
        self.model.set_logger(Logger(folder=None, output_formats=[]))

    def run(self) -> tuple[float, float, str]:
        fill_sb3_buffer(self.model, random_rollout(1, self.samples, self.generator))
        wall, cpu, _ = timed(self.model.train)
        success = self.model.logger.name_to_value.get("train/is_line_search_success", float("nan"))
        return wall, cpu, f"accepted={success:.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=16_000, help="transitions per batch")
    parser.add_argument("--repeats", type=int, default=5, help="timed updates after a warm-up")
    parser.add_argument("--fisher-fraction", type=float, default=None,
                        help="also time ours with the Fisher products on this share of the batch "
                             "(algo.fisher_fraction)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", category=UserWarning)

    print(f"batch: {args.samples} samples, obs {OBSERVATION_DIM}, action {ACTION_DIM}")
    print("settings (both): " + ", ".join(f"{k}={v}" for k, v in SETTINGS.items()))
    contenders = [SB3Update(args.samples), OurUpdate(args.samples)]
    if args.fisher_fraction is not None:
        contenders.append(OurUpdate(args.samples, args.fisher_fraction))
    wall: dict[str, list[float]] = {c.name: [] for c in contenders}
    cpu: dict[str, list[float]] = {c.name: [] for c in contenders}
    # Alternate the two, so load from other processes on a shared machine hits both alike.
    for repeat in range(args.repeats + 1):
        for contender in contenders:
            elapsed, cpu_elapsed, note = contender.run()
            label = "warm-up" if repeat == 0 else f"rep {repeat}"
            print(f"  {contender.name} {label:7s}: {elapsed:.3f} s wall, {cpu_elapsed:.3f} s cpu  {note}")
            if repeat > 0:
                wall[contender.name].append(elapsed)
                cpu[contender.name].append(cpu_elapsed)
    median_wall = {name: statistics.median(times) for name, times in wall.items()}
    median_cpu = {name: statistics.median(times) for name, times in cpu.items()}
    print(f"sb3-contrib TRPO.train() median: {median_wall['sb3']:.3f} s wall, {median_cpu['sb3']:.3f} s cpu")
    print(f"unipolicy_rl TRPOUpdater.update() median: {median_wall['ours']:.3f} s wall, {median_cpu['ours']:.3f} s cpu")
    print(f"cpu-time ratio (ours/sb3): {median_cpu['ours'] / median_cpu['sb3']:.3f}")
    print(f"trpo_update_ratio: {median_wall['ours'] / median_wall['sb3']:.3f}")
    if args.fisher_fraction is not None:
        name = contenders[-1].name
        print(f"{name} / ours, cpu-time ratio: {median_cpu[name] / median_cpu['ours']:.3f}")


if __name__ == "__main__":
    main()
