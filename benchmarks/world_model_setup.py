"""What the world-model benchmarks share: real gait-plus-noise episodes on SE robots, and the
models and trainer settings as ``conf/world_model/`` configures them.

Not a benchmark itself: ``model_fit.py``, ``imagination_throughput.py`` and
``model_accuracy.py`` import it. Every robot's design is drawn from the SE ranges
(``DesignDistribution()``) at each episode start; its actions are the open-loop gait
(:class:`~unipolicy_rl.envs.gait.SineGait`, which walks) plus Gaussian noise, clipped to
[-1, 1], so the data both walks and varies. Episodes are 100 actions, stepped by
``SleepingParallelEnv`` workers of ``BatchedWalkerEnv(full_state=True)`` robots.

Collections are cached under ``/tmp/unipolicy_rl_benchmarks/`` (never the repository), keyed
by their settings, so a rerun skips the physics; the cache keeps the collection's rate.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from env_throughput import ReplayedActions
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tensordict import TensorDict

from unipolicy_rl.collectors import transitions
from unipolicy_rl.envs import BatchedWalkerEnv, DesignDistribution, PhysicsSettings, SleepingParallelEnv
from unipolicy_rl.envs.gait import SineGait
from unipolicy_rl.world_models import CellEnsemble, DynamicsModel, StateLayout

CACHE = Path("/tmp/unipolicy_rl_benchmarks")
EPISODE_LENGTH = 100
CONFIGS = Path(__file__).resolve().parent.parent / "conf" / "world_model"


def trainer_settings(world_model: str) -> dict:
    """``conf/world_model/<world_model>.yaml``'s trainer settings (the yaml is their one source)."""
    settings = OmegaConf.to_container(OmegaConf.load(CONFIGS / f"{world_model}.yaml").trainer)
    settings.pop("_target_")
    return settings


def make_trainer(world_model: str, **overrides):
    """``conf/world_model/<world_model>.yaml``'s trainer (``ModelTrainer`` or ``PCETrainer``), ``overrides`` applied."""
    return instantiate(OmegaConf.load(CONFIGS / f"{world_model}.yaml").trainer, **overrides)


def configured_trainer(world_model: str, threads: int, max_epochs: int | None = None):
    """The yaml's trainer on ``threads`` threads, its epochs capped at ``max_epochs`` where it has
    epochs (a closed-form PCE trainer has none)."""
    overrides = {"num_threads": threads}
    if max_epochs is not None and "max_epochs" in OmegaConf.load(CONFIGS / f"{world_model}.yaml").trainer:
        overrides["max_epochs"] = max_epochs
    return make_trainer(world_model, **overrides)


def configured(world_model: str, layout: StateLayout, threads: int, max_epochs: int | None = None):
    """``conf/world_model/<world_model>.yaml``'s model, predicting ``layout``, and its trainer
    (:func:`configured_trainer`): the yaml is their one source."""
    return default_model(layout, world_model), configured_trainer(world_model, threads, max_epochs)


def default_model(layout: StateLayout, world_model: str = "moe") -> DynamicsModel:
    """``world_model=moe``'s model (a ``GaussianEnsemble``) from its yaml, predicting ``layout``;
    another ``world_model`` (``"pce"``) gives that yaml's model the same way."""
    return instantiate(OmegaConf.load(CONFIGS / f"{world_model}.yaml").model, _partial_=True, _convert_="all")(
        layout=layout, action_dim=4)


def thesis_model(layout: StateLayout) -> CellEnsemble:
    """``world_model=moe_thesis``'s model: 6 x 6 cells over the SE ranges (the yaml takes them
    from ``evaluation``, which a lone yaml cannot resolve), 2 x 200 ReLU position and velocity networks."""
    model = OmegaConf.load(CONFIGS / "moe_thesis.yaml").model
    design = DesignDistribution()
    return CellEnsemble(layout, 4, design.length_range, design.density_range, divisions=model.divisions,
                        hidden=tuple(model.hidden), activation=model.activation)


@dataclass
class Collection:
    """``episodes``: ``[E, 100]`` with ``state``, ``action``, ``design``, ``("next", "state")`` and
    ``("next", "physics_fault")`` (states in the env's ``full`` layout). ``seconds`` and
    ``actions_per_second`` are the collection's own (from the cache when ``cached``)."""

    episodes: TensorDict
    seconds: float
    actions_per_second: float
    cached: bool

    def transitions(self, state_of=lambda state: state) -> TensorDict:
        """One row per real step (state, action, design, next_state, episode_start), faults
        left out: the model-based collector's own :func:`~unipolicy_rl.collectors.transitions`."""
        return transitions(self.episodes, state_of)


def gait_actions(rounds_shape: tuple[int, ...], noise: float, generator: torch.Generator) -> torch.Tensor:
    """``[100, *rounds_shape, 4]``: the gait at each step of an episode plus N(0, noise^2), clipped."""
    period = PhysicsSettings().control_period
    gait = torch.from_numpy(np.stack([SineGait().action(step, period) for step in range(EPISODE_LENGTH)])).float()
    gait = gait.reshape(EPISODE_LENGTH, *([1] * len(rounds_shape)), gait.shape[-1])
    jitter = torch.randn((EPISODE_LENGTH, *rounds_shape, gait.shape[-1]), generator=generator) * noise
    return (gait + jitter).clamp(-1.0, 1.0)


def collect(episodes: int, noise: float = 0.3, seed: int = 0, workers: int = 2, robots: int = 32,
            cache: bool = True) -> Collection:
    """``episodes`` gait-plus-noise episodes on SE robots (rounded up to whole rounds of
    ``workers x robots``, then cut back), from the cache when it has them."""
    path = CACHE / f"gait_e{episodes}_n{noise}_s{seed}_w{workers}_r{robots}.pt"
    if cache and path.exists():
        saved = torch.load(path, weights_only=False)
        return Collection(saved["episodes"], saved["seconds"], saved["actions_per_second"], cached=True)
    make_env = functools.partial(BatchedWalkerEnv, robots, DesignDistribution(), full_state=True)
    threads = torch.get_num_threads()  # a ParallelEnv sets its parent's torch threads to its worker count
    env = SleepingParallelEnv(workers, make_env, mp_start_method="fork") if workers > 1 else make_env()
    env.set_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    per_round = env.batch_size.numel()
    rounds = -(-episodes // per_round)
    keep = ["state", "action", "design", ("next", "state"), ("next", "physics_fault")]
    chunks = []
    env.rollout(2, break_when_any_done=False)  # untimed: worker start-up
    started = time.perf_counter()
    for _ in range(rounds):
        policy = ReplayedActions(gait_actions(tuple(env.batch_size), noise, generator))
        # Each rollout starts with a reset: every robot gets a new SE design for its episode.
        rollout = env.rollout(EPISODE_LENGTH, policy, break_when_any_done=False)
        chunks.append(rollout.select(*keep).reshape(-1, EPISODE_LENGTH).clone())
    seconds = time.perf_counter() - started
    env.close()
    torch.set_num_threads(threads)
    data = torch.cat(chunks)[:episodes]
    rate = rounds * per_round * EPISODE_LENGTH / seconds
    if cache:
        CACHE.mkdir(parents=True, exist_ok=True)
        torch.save({"episodes": data, "seconds": seconds, "actions_per_second": rate}, path)
    return Collection(data, seconds, rate, cached=False)
