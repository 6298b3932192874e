"""Checkpoints: written atomically, resumable, and loadable as a policy in one call.

A checkpoint holds everything a run needs to continue bit-for-bit (the learner's state: weights,
optimisers, observation statistics, RNG; the collector's position; for a model-based run its
world model and replay buffer; the best periodic evaluation so far) and its resolved config, so
``load_policy(path)`` can rebuild the policy without any other file. Its layout is defined here
and nowhere else: :func:`training_state` writes it (with ``resumable=False``, the policy
alone), :func:`restore_training_state` reads it back, and older formats are read through
:func:`_upgraded`.

This module imports no collector, world model or learner: loading a policy to run or evaluate
it needs only :mod:`unipolicy_rl.policy` and the env.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.envs.batched import BatchedWalkerEnv
from unipolicy_rl.envs.config import env_builder
from unipolicy_rl.policy import (
    TOKEN_POLICIES,
    make_collecting_policy,
    make_observation_norm,
    make_policy_actor,
    make_token_actor,
    make_token_norm,
    pin_token_critic,
    policy_architecture,
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


# 1: weights, statistics, critic optimiser and epoch; 2: adds the collector's state; 3: the policy,
# the learner, the collector and the world model each under their own key.
CHECKPOINT_FORMAT = 3


def load_checkpoint(path: str | Path) -> dict:
    """The checkpoint at ``path`` in the current layout (older formats are upgraded on reading)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {str(path)!r}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # pickle, zip and torch errors alike: the file is not ours or is cut short
        raise ValueError(f"{str(path)!r} is not a readable checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict) or not ({"actor", "policy"} & state.keys()) or "config" not in state:
        raise ValueError(f"{str(path)!r} is not a unipolicy_rl checkpoint (no policy weights and config in it)")
    if state.get("format", 1) > CHECKPOINT_FORMAT:
        raise ValueError(f"{str(path)!r} has checkpoint format {state['format']}, newer than this version's "
                         f"{CHECKPOINT_FORMAT}: update unipolicy_rl to read it")
    return _upgraded(state)


def training_state(*, epoch: int, elapsed: float, config: dict, observation_dim: int, action_dim: int, learner,
                   collector, world=None, best_evaluation: dict | None = None, resumable: bool = True) -> dict:
    """Everything a run continues from, after ``epoch`` real epochs and ``elapsed`` wall seconds.

    ``observation_dim`` and ``action_dim`` are the policy's sizes: for a token policy the
    features per token ``F`` and the padded number of tokens ``L`` (what
    :func:`~unipolicy_rl.factories.probe_dimensions` reads off the env), so :func:`load_policy`
    rebuilds it with ``make_token_actor(cfg, F, L)``.
    ``learner`` is a :class:`~unipolicy_rl.learners.Learner`, ``collector`` the real collector,
    ``world`` a model-based run's :class:`~unipolicy_rl.factories.WorldModelParts` (or None), and
    ``best_evaluation`` the best periodic grid evaluation so far (epoch, grid mean and worst).
    ``resumable=False`` writes the policy alone, marked so a resume from it is refused, without
    asking the learner, collector or world model for their state."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "epoch": epoch,
        "elapsed": elapsed,
        "config": config,
        "observation_dim": observation_dim,
        "action_dim": action_dim,
        "policy": learner.policy_state(),
        "best_evaluation": best_evaluation,
    }
    if not resumable:
        return {**state, "resumable": False}
    state["learner"], state["collector"] = learner.state_dict(), collector.state_dict()
    if world is not None:
        state["world_model"] = world.model.state_dict()
        state["replay_buffer"] = world.buffer.state_dict()
    return state


# What a checkpoint holds beyond the policy: the state a run continues from.
RUN_STATE = ("learner", "collector", "world_model", "replay_buffer")


def policy_only(state: dict) -> dict:
    """``state`` without what only a resume needs (:data:`RUN_STATE`), marked not resumable: the
    policy, its config and sizes, which :func:`load_policy` reads."""
    return {**{key: value for key, value in state.items() if key not in RUN_STATE}, "resumable": False}


def check_resumable(state: dict, path: str | Path) -> None:
    if not state.get("resumable", True):
        raise ValueError(f"{str(path)!r} holds a policy only (the best periodic evaluation's), not a run to "
                         f"resume: resume from the run's checkpoint.pt, or evaluate this one with "
                         f"python -m unipolicy_rl.evaluate")


def restore_training_state(state: dict, *, learner, collector, world=None) -> None:
    """Loads what :func:`training_state` saved back into the run's parts."""
    learner.load_state_dict(state["learner"])
    collector.load_state_dict(state["collector"])
    if world is not None:
        world.model.load_state_dict(state["world_model"])
        world.buffer.load_state_dict(state["replay_buffer"])
    if state.get("model_phase_skipped"):
        print(f"resume: this checkpoint (format 2) was written before epoch {state['epoch']}'s model fit and "
              f"imagined updates; the run goes on with epoch {state['epoch'] + 1}")


class RunCheckpoints:
    """A run folder's checkpoints: ``checkpoint.pt`` (the whole run, resumable) and ``best.pt``
    (the policy alone of the best periodic evaluation, kept apart: a run that walks and then falls
    back still hands over its best policy). Both carry the run's wall time so far, over resumes.

    Args:
        run_dir: the run folder.
        config: the run's resolved config (a plain dict).
        observation_dim, action_dim: the env's sizes.
        learner, collector, world: the run's parts (``world`` None for a real source).
        elapsed_before: wall seconds of the run before this process (a resumed run's).
    """

    def __init__(self, run_dir: Path, *, config: dict, observation_dim: int, action_dim: int, learner, collector,
                 world=None, elapsed_before: float = 0.0) -> None:
        self.path, self.best_path = run_dir / "checkpoint.pt", run_dir / "best.pt"
        self.parts = {"config": config, "observation_dim": observation_dim, "action_dim": action_dim,
                      "learner": learner, "collector": collector, "world": world}
        self.elapsed_before = elapsed_before
        self.started = time.perf_counter()

    def elapsed(self) -> float:
        return self.elapsed_before + time.perf_counter() - self.started

    def state(self, best_evaluation: dict | None, resumable: bool = True) -> dict:
        return training_state(epoch=self.parts["collector"].epoch, elapsed=self.elapsed(),
                              best_evaluation=best_evaluation, resumable=resumable, **self.parts)

    def save(self, best_evaluation: dict | None) -> Path:
        return save_checkpoint(self.path, self.state(best_evaluation))

    def save_best(self, best_evaluation: dict) -> Path:
        return save_checkpoint(self.best_path, self.state(best_evaluation, resumable=False))


def _upgraded(state: dict) -> dict:
    """A format 1 or 2 checkpoint in the current layout (format 2 kept the policy's and the
    learner's parts at the top and a model-based collector's model and buffer inside its state;
    format 1 had no collector state, only the epoch)."""
    if state.get("format", 1) >= 3:
        return state
    old = dict(state)
    state = {key: old[key] for key in ("epoch", "elapsed", "config", "observation_dim", "action_dim", "resumable",
                                       "best_evaluation") if key in old}
    state["format"] = CHECKPOINT_FORMAT
    state["policy"] = {key: old[key] for key in ("actor", "observation_loc", "observation_scale") if key in old}
    if not old.get("resumable", True):  # a policy alone (best.pt)
        return state
    learner_keys = ("actor", "critic", "observation_statistics", "critic_optimizer", "critic_generator")
    state["learner"] = {key: old[key] for key in learner_keys if key in old}
    collector = old.get("collector")
    if collector is None:  # format 1: real data only, just the epoch
        config = old["config"]
        frames = config.get("episodes_per_epoch", 0) * config.get("robot", {}).get("episode_length", 0)
        collector = {"epoch": old["epoch"], "real_env_steps": old["epoch"] * frames}
    if "real" in collector:  # a model-based run's collector
        state["world_model"], state["replay_buffer"] = collector["model"], collector["buffer"]
        state["model_phase_skipped"] = int(collector["model_fitted_for"]) < int(collector["real"]["epoch"])
        collector = collector["real"]
    state["collector"] = collector
    return state


# The settings a checkpoint's weights and model were built for: a resume takes them from the
# checkpoint, whole, and refuses a command line that sets them otherwise. (A dotted key names one
# setting; a bare group name covers the group.)
ARCHITECTURE_KEYS = ("algo.name", "algo.actor_hidden", "algo.critic_hidden", "algo.activation", "policy", "robot",
                     "world_model.model", "world_model.model_state")
# Settings a resume never takes from the checkpoint: where this run resumes from.
NOT_RESUMED = ("resume",)
_ABSENT = object()


def settings_for_resume(cfg: DictConfig, state: dict, overridden: Sequence[str], path: str | Path) -> DictConfig:
    """``cfg`` with the settings of the run that saved ``state``, except those set on this command line.

    A resume continues a run: every setting the command line does not name is the run's own
    (``imagination.fit_every``, ``seed``, ``epochs``, ...), not this configuration's default,
    and the resume prints the ones it took that differ. The networks, robot and world model
    (:data:`ARCHITECTURE_KEYS`) are taken whole, since weights only load into the networks they
    were trained in: a command line that sets them to something else is refused, naming the
    keys, rather than failing in ``load_state_dict``. Any other setting the command line names
    is this run's (``epochs=200`` extends it); an interpolated setting follows the one it names.
    """
    saved = OmegaConf.create(state["config"])
    pin_token_critic(saved)  # a token policy saved before policy.critic existed keeps its critic
    kind, saved_kind = OmegaConf.select(cfg, "source.kind"), OmegaConf.select(saved, "source.kind")
    if saved_kind is not None and kind != saved_kind:
        raise ValueError(f"cannot resume {str(path)!r}: it trained on source.kind={saved_kind!r} data "
                         f"(source={OmegaConf.select(saved, 'source.name')}), this run is {kind!r}")

    def named(key: str) -> bool:
        return any(name == key or name.startswith(f"{key}.") or key.startswith(f"{name}.") for name in overridden)

    resumed = cfg.copy()
    taken, conflicts = [], []
    for key in ARCHITECTURE_KEYS:
        ours, theirs = OmegaConf.select(cfg, key), OmegaConf.select(saved, key)
        if theirs is None or ours == theirs:
            continue
        if named(key):
            conflicts.append(f"{key}: {_show(ours)} here, {_show(theirs)} in the checkpoint")
        else:
            OmegaConf.update(resumed, key, theirs, force_add=True)
            taken.extend(_differences(key, ours, theirs))
    if conflicts:
        raise ValueError(f"cannot resume {str(path)!r} with other network/robot settings ("
                         + "; ".join(conflicts) + "): drop those overrides, or start a new run")
    unknown, settled_groups = [], [*ARCHITECTURE_KEYS, *NOT_RESUMED]

    def take_whole(key: str) -> None:
        value = OmegaConf.select(saved, key).copy()
        ours = OmegaConf.select(cfg, key)
        for name in _setting_keys(ours) if OmegaConf.is_dict(ours) else ():
            if _interpolated(ours, name) and OmegaConf.select(value, name, default=_ABSENT) is not _ABSENT:
                # Where this run writes (``logger.log_dir``) follows this run, not the saved one's folder.
                OmegaConf.update(value, name, _raw(ours, name), merge=False)
        OmegaConf.update(resumed, key, value, merge=False)
        settled_groups.append(key)
        taken.append(f"{key} (a {value._target_})")

    def settled(key: str) -> bool:
        return named(key) or any(key == group or key.startswith(f"{group}.") for group in settled_groups)

    keys = _setting_keys(saved)
    # An object the run built from another class than this configuration does (another logger,
    # another trainer) is taken whole: its settings are that class's, not to be mixed with these.
    for key in keys:
        parent, _, name = key.rpartition(".")
        if name == "_target_" and parent and not settled(parent) and \
                OmegaConf.is_dict(OmegaConf.select(cfg, parent, default=None)) and \
                OmegaConf.select(cfg, key, default=_ABSENT) != OmegaConf.select(saved, key):
            take_whole(parent)
    for key in keys:
        if settled(key) or _interpolated(cfg, key):
            continue
        ours = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_resolution_failure=False)
        if ours is _ABSENT:
            unknown.append(key)
        elif _plain(ours) != _plain(theirs := OmegaConf.select(saved, key)):
            OmegaConf.update(resumed, key, theirs, merge=False)
            taken.append(f"{key}={_show(theirs)}")
    if taken:
        print(f"resume: took {', '.join(taken)} from the checkpoint (the run's own settings)")
    if unknown:
        print(f"resume: the checkpoint's {', '.join(unknown)} are not settings of this configuration "
              f"(another group, or an older version): not used")
    return resumed


def _differences(key: str, ours, theirs) -> list[str]:
    """``key.leaf=value`` for each of ``theirs``'s settings that differs from ``ours`` (``key=value``
    for a setting that is not a group)."""
    if not (OmegaConf.is_dict(theirs) and OmegaConf.is_dict(ours)):
        return [f"{key}={_show(theirs)}"]
    return [f"{key}.{name}={_show(value)}" for name in _setting_keys(theirs)
            if _plain(OmegaConf.select(ours, name, default=None, throw_on_resolution_failure=False))
            != _plain(value := OmegaConf.select(theirs, name))]


def _setting_keys(node: DictConfig, prefix: str = "") -> list[str]:
    """The dotted keys of ``node``'s settings: its leaves, a list counting as one."""
    keys = []
    for name in node:
        key, child = f"{prefix}{name}", node._get_node(name)
        if OmegaConf.is_dict(child) and not child._is_interpolation():
            keys.extend(_setting_keys(child, f"{key}."))
        else:
            keys.append(key)
    return keys


def _interpolated(cfg: DictConfig, key: str) -> bool:
    """Whether setting ``key`` of ``cfg`` is an interpolation (``${...}``), unresolved."""
    parent, _, name = key.rpartition(".")
    node = OmegaConf.select(cfg, parent, default=None, throw_on_resolution_failure=False) if parent else cfg
    return OmegaConf.is_dict(node) and name in node and OmegaConf.is_interpolation(node, name)


def _raw(cfg: DictConfig, key: str) -> str:
    parent, _, name = key.rpartition(".")
    return (OmegaConf.select(cfg, parent) if parent else cfg)._get_node(name)._value()


def _plain(value):
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _show(value) -> str:
    return repr(_plain(value))


@dataclass
class LoadedPolicy:
    """A trained policy, ready to act.

    ``policy`` reads the raw ``observation`` (normalisation is inside it), or for a token policy
    the raw ``tokens`` with their masks and parents, and writes ``action``;
    ``env_class(num_robots, **env_kwargs)`` rebuilds the environment it was trained on
    (``BatchedWalkerEnv``, or ``MorphologyWalkerEnv`` for ``robot=grammar``).
    """

    policy: TensorDictModuleBase
    env_kwargs: dict
    config: dict
    epoch: int
    env_class: type = BatchedWalkerEnv

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """Action for one WalkerEnv observation (or a batch of them); a flat policy's only."""
        if self.env_class is not BatchedWalkerEnv:
            raise ValueError(f"act() takes a flat WalkerEnv observation; this policy reads the link tokens of a "
                             f"{self.env_class.__name__}: call .policy on a tensordict of the env's keys")
        observation = torch.as_tensor(np.asarray(observation), dtype=torch.float32)
        td = TensorDict({"observation": observation}, batch_size=observation.shape[:-1])
        mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
        with torch.no_grad(), set_exploration_type(mode):
            return self.policy(td)["action"].numpy()


def load_policy(path: str | Path, device: str = "cpu") -> LoadedPolicy:
    """Rebuilds the trained policy from a checkpoint: ``load_policy(p).act(obs)``; a token policy
    from its architecture (``policy``) and its sizes ``F`` and ``L`` (``observation_dim``, ``action_dim``)."""
    state = load_checkpoint(path)
    cfg = OmegaConf.create(state["config"])
    policy = state["policy"]
    dims, loc, scale = (state["observation_dim"], state["action_dim"]), policy["observation_loc"], \
        policy["observation_scale"]
    if policy_architecture(cfg) in TOKEN_POLICIES:
        actor = make_token_actor(cfg, *dims)
        normalizer = make_token_norm(dims[0], loc, scale)
    else:
        actor = make_policy_actor(cfg, *dims)
        normalizer = make_observation_norm(dims[0], loc, scale)
    actor.load_state_dict(policy["actor"])
    policy = make_collecting_policy(normalizer, actor).to(device).eval()
    env_class, kwargs = env_builder(cfg)
    return LoadedPolicy(policy, kwargs, state["config"], state["epoch"], env_class)
