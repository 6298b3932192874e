"""Checkpoints: written atomically, resumable, and loadable as a policy in one call.

A checkpoint holds everything a run needs to continue bit-for-bit (weights, critic
optimiser, observation statistics, the critic's minibatch RNG, the collector's position
and, for a model-based run, its world model and replay buffer) and its resolved config, so
``load_policy(path)`` can rebuild the policy without any other file. Its layout is defined
once, by :func:`training_state` and :func:`restore_training_state`.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.factories import (
    config_from_dict,
    env_kwargs,
    make_actor_critic,
    make_collecting_policy,
    make_observation_norm,
)


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Writes ``state`` next to ``path`` and renames it into place, so a crash or Ctrl-C
    mid-write never leaves a truncated checkpoint behind."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            torch.save(state, file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


# 1: weights, statistics, critic optimiser and epoch; 2: adds the collector's state.
CHECKPOINT_FORMAT = 2


def load_checkpoint(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {str(path)!r}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # pickle, zip and torch errors alike: the file is not ours or is cut short
        raise ValueError(f"{str(path)!r} is not a readable checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict) or "actor" not in state or "config" not in state:
        raise ValueError(f"{str(path)!r} is not a unipolicy_rl checkpoint (no policy weights and config in it)")
    if state.get("format", 1) > CHECKPOINT_FORMAT:
        raise ValueError(f"{str(path)!r} has checkpoint format {state['format']}, newer than this version's "
                         f"{CHECKPOINT_FORMAT}: update unipolicy_rl to read it")
    return state


def training_state(*, epoch: int, config: dict, observation_dim: int, action_dim: int, actor, critic, statistics,
                   updater, collector, elapsed: float) -> dict:
    """Everything a run continues from, after ``epoch`` real epochs and ``elapsed`` wall seconds
    (``collector=None``: all but the collector's state, for :func:`policy_only`)."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "epoch": epoch,
        "elapsed": elapsed,
        "config": config,
        "observation_dim": observation_dim,
        "action_dim": action_dim,
        "actor": actor.state_dict(),
        "critic": critic.state_dict(),
        "observation_statistics": statistics.state_dict(),
        "observation_loc": statistics.loc,
        "observation_scale": statistics.scale,
        "critic_optimizer": updater.critic_optimizer.state_dict(),
        "critic_generator": updater.generator.get_state(),
    }
    if collector is not None:
        state["collector"] = collector.state_dict()
    return state


def policy_only(state: dict) -> dict:
    """A training state without the collector (replay buffer, world model): enough for
    :func:`load_policy` and evaluation, marked so a resume from it is refused."""
    return {**{key: value for key, value in state.items() if key != "collector"}, "resumable": False}


def check_resumable(state: dict, path: str | Path) -> None:
    if not state.get("resumable", True):
        raise ValueError(f"{str(path)!r} holds a policy only (the best periodic evaluation's), not a run to "
                         f"resume: resume from the run's checkpoint.pt, or evaluate this one with "
                         f"python -m unipolicy_rl.evaluate")


def restore_training_state(state: dict, *, actor, critic, statistics, updater) -> None:
    """Loads what :func:`training_state` saved into the learner's parts (the collector loads
    ``state["collector"]`` itself, see :func:`collector_state`)."""
    actor.load_state_dict(state["actor"])
    critic.load_state_dict(state["critic"])
    statistics.load_state_dict(state["observation_statistics"])
    updater.critic_optimizer.load_state_dict(state["critic_optimizer"])
    updater.generator.set_state(state["critic_generator"])


# The settings a checkpoint's weights and model were built for: a resume takes them from the
# checkpoint. (A dotted key names one setting; a bare group name covers the group.)
ARCHITECTURE_KEYS = ("algo.actor_hidden", "algo.critic_hidden", "algo.activation", "robot", "world_model.model",
                     "world_model.model_state")


def settings_for_resume(cfg: DictConfig, state: dict, overridden: Sequence[str], path: str | Path) -> DictConfig:
    """``cfg`` with the checkpoint's network, robot and world-model settings (:data:`ARCHITECTURE_KEYS`).

    Weights only load into the networks they were trained in, so a resume rebuilds those,
    and says which settings it took. A setting the user overrode on the command line to
    something else is refused, naming the keys, rather than failing in ``load_state_dict``.
    """
    saved = OmegaConf.create(state["config"])
    kind, saved_kind = OmegaConf.select(cfg, "source.kind"), OmegaConf.select(saved, "source.kind")
    if saved_kind is not None and kind != saved_kind:
        raise ValueError(f"cannot resume {str(path)!r}: it trained on source.kind={saved_kind!r} data "
                         f"(source={OmegaConf.select(saved, 'source.name')}), this run is {kind!r}")
    resumed = cfg.copy()
    taken, conflicts = [], []
    for key in ARCHITECTURE_KEYS:
        ours, theirs = OmegaConf.select(cfg, key), OmegaConf.select(saved, key)
        if theirs is None or ours == theirs:
            continue
        explicit = [name for name in overridden if name == key or name.startswith(f"{key}.")
                    or key.startswith(f"{name}.")]
        if explicit:
            conflicts.append(f"{key}: {_show(ours)} here, {_show(theirs)} in the checkpoint")
        else:
            OmegaConf.update(resumed, key, theirs, force_add=True)
            taken.append(key)
    if conflicts:
        raise ValueError(f"cannot resume {str(path)!r} with other network/robot settings ("
                         + "; ".join(conflicts) + "): drop those overrides, or start a new run")
    if taken:
        print(f"resume: took {', '.join(taken)} from the checkpoint (its weights were trained with them)")
    return resumed


def _show(value) -> str:
    return repr(OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value)


def collector_state(state: dict) -> dict:
    """The collector's saved state; a format-1 checkpoint (real data only) had just its epoch."""
    if "collector" in state:
        return state["collector"]
    config = state["config"]
    frames = config["episodes_per_epoch"] * config["robot"]["episode_length"]
    return {"epoch": state["epoch"], "real_env_steps": state["epoch"] * frames}


@dataclass
class LoadedPolicy:
    """A trained policy, ready to act.

    ``policy`` reads the raw ``observation`` (normalisation is inside it) and writes
    ``action``; ``env_kwargs`` rebuild the environment it was trained on.
    """

    policy: TensorDictModuleBase
    env_kwargs: dict
    config: dict
    epoch: int

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """Action for one WalkerEnv observation (or a batch of them)."""
        observation = torch.as_tensor(np.asarray(observation), dtype=torch.float32)
        td = TensorDict({"observation": observation}, batch_size=observation.shape[:-1])
        mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
        with torch.no_grad(), set_exploration_type(mode):
            return self.policy(td)["action"].numpy()


def load_policy(path: str | Path, device: str = "cpu") -> LoadedPolicy:
    """Rebuilds the trained policy from a checkpoint: ``load_policy(p).act(obs)``."""
    state = load_checkpoint(path)
    cfg = config_from_dict(state["config"])
    actor, _ = make_actor_critic(cfg, state["observation_dim"], state["action_dim"])
    actor.load_state_dict(state["actor"])
    normalizer = make_observation_norm(state["observation_dim"], state["observation_loc"], state["observation_scale"])
    policy = make_collecting_policy(normalizer, actor).to(device).eval()
    return LoadedPolicy(policy, env_kwargs(cfg), state["config"], state["epoch"])
