"""Checkpoints: written atomically, resumable, and loadable as a policy in one call.

A checkpoint holds everything a run needs to continue bit-for-bit (weights, critic
optimiser, observation statistics, the critic's minibatch RNG, epoch) and its resolved config, so
``load_policy(path)`` can rebuild the policy without any other file.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
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


def load_checkpoint(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {str(path)!r}")
    return torch.load(path, map_location="cpu", weights_only=False)


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
