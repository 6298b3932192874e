"""What the world-model benchmarks share: real gait-plus-noise episodes on SE robots, and the
models and trainers exactly as a training run builds them.

Not a benchmark itself: ``model_fit.py``, ``imagination_throughput.py``, ``model_accuracy.py``,
``branch_accuracy.py``, ``pce_fit.py`` and ``surrogate_accuracy.py`` import it. A model and its
trainer come from the config ``python train.py source=moe world_model=<name>`` composes (Hydra's
``compose``, the benchmark's settings as overrides) and from the factory training uses
(:func:`unipolicy_rl.factories.make_dynamics_model`), so a benchmark measures what a run
trains. Every robot's design is drawn from the SE ranges (``DesignDistribution()``) at each
episode start; its actions are the open-loop gait (:class:`~unipolicy_rl.envs.gait.SineGait`,
which walks) plus Gaussian noise, clipped to [-1, 1], so the data both walks and varies.
Episodes are 100 actions, stepped by ``SleepingParallelEnv`` workers of
``BatchedWalkerEnv(full_state=True)`` robots.

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
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict

from unipolicy_rl.collectors import transitions
from unipolicy_rl.envs import BatchedWalkerEnv, DesignDistribution, PhysicsSettings, SleepingParallelEnv
from unipolicy_rl.envs.gait import SineGait
from unipolicy_rl.factories import make_dynamics_model
from unipolicy_rl.world_models import Dynamics
from unipolicy_rl.world_models.trainer import Trainer

CACHE = Path("/tmp/unipolicy_rl_benchmarks")
EPISODE_LENGTH = 100
CONF = Path(__file__).resolve().parent.parent / "conf"


def world_model_config(world_model: str, threads: int | None = None, max_epochs: int | None = None,
                       model_state: str | None = None, overrides: tuple[str, ...] = ()) -> DictConfig:
    """The config of ``python train.py source=moe world_model=<world_model>`` with the
    benchmark's settings as overrides: the trainer's ``num_threads`` (None: the yaml's), its
    ``max_epochs`` where it has epochs (a closed-form PCE trainer has none), the model's
    ``model_state`` (None: the yaml's) and any further ``overrides``."""
    settings = [*(() if threads is None else (f"world_model.trainer.num_threads={threads}",)),
                *(() if model_state is None else (f"world_model.model_state={model_state}",)), *overrides]
    cfg = _composed(world_model, settings)
    if max_epochs is not None and "max_epochs" in cfg.world_model.trainer:
        cfg = _composed(world_model, [*settings, f"world_model.trainer.max_epochs={max_epochs}"])
    return cfg


def _composed(world_model: str, overrides: list[str]) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=["source=moe", f"world_model={world_model}", *overrides])


def model_of(cfg: DictConfig, device: torch.device | str = "cpu") -> Dynamics:
    """``cfg``'s world model, sized for its robot, through training's factory."""
    return make_dynamics_model(cfg, len(cfg.robot.settings.actuated), device=device)


def trainer_of(cfg: DictConfig) -> Trainer:
    """``cfg``'s world-model trainer (``ModelTrainer``, ``ClosedFormTrainer``), as training builds it."""
    return instantiate(cfg.world_model.trainer)


def make_model(world_model: str = "moe", model_state: str | None = None,
               device: torch.device | str = "cpu") -> Dynamics:
    """``world_model=<world_model>``'s model (``moe``: a ``GaussianEnsemble``; ``moe_thesis``: the
    thesis' ``CellEnsemble``; ``pce``, ``pce_thesis``), predicting ``model_state`` (None: the yaml's)."""
    return model_of(world_model_config(world_model, model_state=model_state), device)


def make_trainer(world_model: str, threads: int | None = None, max_epochs: int | None = None) -> Trainer:
    """``world_model=<world_model>``'s trainer on ``threads`` threads, its epochs capped at ``max_epochs``."""
    return trainer_of(world_model_config(world_model, threads, max_epochs))


def trainer_settings(world_model: str, threads: int | None = None, max_epochs: int | None = None) -> dict:
    """The settings of :func:`make_trainer`'s trainer, for a benchmark's printout."""
    settings = OmegaConf.to_container(world_model_config(world_model, threads, max_epochs).world_model.trainer)
    settings.pop("_target_")
    return settings


def configured(world_model: str, threads: int | None = None, max_epochs: int | None = None,
               model_state: str | None = None, device: torch.device | str = "cpu",
               overrides: tuple[str, ...] = ()) -> tuple[Dynamics, Trainer]:
    """``world_model=<world_model>``'s model and trainer from one composed config (see
    :func:`world_model_config` for the settings; ``overrides`` such as
    ``world_model.model.divisions=1``)."""
    cfg = world_model_config(world_model, threads, max_epochs, model_state, overrides)
    return model_of(cfg, device), trainer_of(cfg)


def parse_model(spec: str) -> tuple[str, tuple[str, ...]]:
    """A benchmark's model spec ``NAME[:key=value,...]`` -> (the ``world_model`` yaml, overrides of
    its ``world_model.model``, or of its trainer where the key starts ``trainer.``):
    ``pce:lags=1,order=4`` is ``world_model=pce`` with ``world_model.model.lags=1
    world_model.model.order=4``; ``moe:trainer.max_epochs=20`` caps the ensemble's fit."""
    name, _, settings = spec.partition(":")
    overrides = []
    for setting in filter(None, settings.split(",")):
        key, equals, value = setting.partition("=")
        if not (key and equals and value):
            raise ValueError(f"a model spec is NAME[:key=value,...], got {spec!r} (bad setting {setting!r})")
        overrides.append(f"world_model.{key if key.startswith('trainer.') else f'model.{key}'}={value}")
    if not (CONF / "world_model" / f"{name}.yaml").exists():
        raise ValueError(f"model spec {spec!r}: no conf/world_model/{name}.yaml")
    return name, tuple(overrides)


def configured_spec(spec: str, threads: int | None = None) -> tuple[Dynamics, Trainer]:
    """The model and trainer of a model spec (:func:`parse_model`), as :func:`configured` builds them."""
    name, overrides = parse_model(spec)
    return configured(name, threads, overrides=overrides)


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
