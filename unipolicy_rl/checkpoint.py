"""Checkpoints: written atomically, resumable, and loadable as a policy in one call.

A checkpoint holds everything a run needs to continue bit-for-bit (the learner's state: weights,
optimisers, observation statistics, RNG; the collector's position; for a model-based run its
world model and replay buffer; the best periodic evaluation so far) and its resolved config, so
``load_policy(path)`` can rebuild the policy without any other file. Its layout is defined here
and nowhere else: :func:`training_state` writes it (with ``resumable=False``, the policy
alone), :func:`restore_training_state` reads it back, and older formats are read through
:func:`migrate`, the one place that knows them.

This module imports no collector, world model or learner: loading a policy to run or evaluate
it needs only :mod:`unipolicy_rl.policy` and the env.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.env_factories import env_builder
from unipolicy_rl.envs.batched import BatchedWalkerEnv
from unipolicy_rl.policy import (
    TOKEN_POLICIES,
    make_collecting_policy,
    make_observation_norm,
    make_policy_actor,
    make_token_actor,
    make_token_norm,
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
# the learner, the collector and the world model each under their own key; 4: adds the run's Hydra
# group choices (``choices``), so a resume composes the run's own config from the checkpoint alone.
CHECKPOINT_FORMAT = 4


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
    return migrate(state)


def training_state(*, epoch: int, elapsed: float, config: dict, observation_dim: int, action_dim: int, learner,
                   collector, world=None, best_evaluation: dict | None = None, resumable: bool = True,
                   choices: dict | None = None) -> dict:
    """Everything a run continues from, after ``epoch`` real epochs and ``elapsed`` wall seconds.

    ``observation_dim`` and ``action_dim`` are the policy's sizes: for a token policy the
    features per token ``F`` and the padded number of tokens ``L`` (what
    :func:`~unipolicy_rl.factories.probe_dimensions` reads off the env), so :func:`load_policy`
    rebuilds it with ``make_token_actor(cfg, F, L)``.
    ``learner`` is a :class:`~unipolicy_rl.learners.Learner`, ``collector`` the real collector,
    ``world`` a model-based run's :class:`~unipolicy_rl.factories.WorldModelParts` (or None), and
    ``best_evaluation`` the best periodic grid evaluation so far (epoch, grid mean and worst).
    ``resumable=False`` writes the policy alone, marked so a resume from it is refused, without
    asking the learner, collector or world model for their state. ``choices`` are the run's Hydra
    group choices (``{"algo": "ppo", "source": "moe", ...}``), which a resume composes its config from."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "epoch": epoch,
        "elapsed": elapsed,
        "config": config,
        "choices": dict(choices or {}),
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
        choices: the run's Hydra group choices.
        observation_dim, action_dim: the env's sizes.
        learner, collector, world: the run's parts (``world`` None for a real source).
        elapsed_before: wall seconds of the run before this process (a resumed run's).
    """

    def __init__(self, run_dir: Path, *, config: dict, observation_dim: int, action_dim: int, learner, collector,
                 world=None, elapsed_before: float = 0.0, choices: dict | None = None) -> None:
        self.path, self.best_path = run_dir / "checkpoint.pt", run_dir / "best.pt"
        self.parts = {"config": config, "choices": choices, "observation_dim": observation_dim,
                      "action_dim": action_dim, "learner": learner, "collector": collector, "world": world}
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


def migrate(state: dict) -> dict:
    """A checkpoint of any earlier format in the current layout, one format at a time, its config
    given the settings added after it was written (:func:`settings_of_its_time`): the one place
    that knows the old layouts and configs."""
    state = dict(state)
    if state.get("format", 1) < 3:
        state = _format_3(state)
    if state["format"] < 4:
        state = {**state, "format": 4, "choices": _choices_of(state["config"])}
    return {**state, "config": settings_of_its_time(state["config"])}


# Settings added after runs had been saved, each with the value that means what those runs did.
# (node, key, value, which configs it applies to)
SETTINGS_BEFORE_THEY_EXISTED = (
    ("algo", "name", "trpo", lambda config: True),  # the first runs were TRPO's
    ("policy", "name", "mlp", lambda config: True),  # before the policy group: the flat MLPs
    ("env", "kind", "walker", lambda config: True),  # before env=gym: the walker
    # TRPO's and PPO's: advantages standardised over the whole batch, the Fisher product on the whole
    # batch, the critic fitted in the update
    ("algo", "advantage_groups", None, lambda config: config["algo"]["name"] in ("trpo", "ppo")),
    ("algo", "fisher_fraction", 1.0, lambda config: config["algo"]["name"] == "trpo"),
    ("algo", "critic_fit", "inline", lambda config: config["algo"]["name"] in ("trpo", "ppo")),
    # grammar robots: links fill the first token slots in link order
    ("robot", "token_layout", "packed", lambda config: config.get("robot", {}).get("kind") == "grammar"),
)


def settings_of_its_time(config: dict) -> dict:
    """``config`` with every setting of :data:`SETTINGS_BEFORE_THEY_EXISTED` it lacks, set to what its
    run did before the setting existed; the builders then read every setting as today's configs
    have it."""
    config = {key: dict(value) if isinstance(value, dict) else value for key, value in config.items()}
    for node, key, value, applies in SETTINGS_BEFORE_THEY_EXISTED:
        if not isinstance(config.get(node), dict):
            config[node] = {}
        if key not in config[node] and applies(config):
            config[node][key] = value
    return config


def _format_3(old: dict) -> dict:
    """A format 1 or 2 checkpoint in format 3's layout (format 2 kept the policy's and the
    learner's parts at the top and a model-based collector's model and buffer inside its state;
    format 1 had no collector state, only the epoch)."""
    state = {key: old[key] for key in ("epoch", "elapsed", "config", "observation_dim", "action_dim", "resumable",
                                       "best_evaluation") if key in old}
    state["format"] = 3
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


def _choices_of(config: dict) -> dict:
    """The group choices a format 3 config shows by itself (each of these groups names its file in
    a ``name`` or ``kind``); the others (design, world model, imagination, logger) a resume takes
    setting by setting from the config."""
    groups = {"algo": ("algo", "name"), "source": ("source", "name"), "policy": ("policy", "name")}
    choices = {group: config.get(node, {}).get(key) for group, (node, key) in groups.items()}
    if isinstance(config.get("robot"), dict):
        choices["robot"] = config["robot"].get("kind", "vertebrate")
    return {group: choice for group, choice in choices.items() if isinstance(choice, str)}


@dataclass
class LoadedPolicy:
    """A trained policy, ready to act.

    ``policy`` reads the raw ``observation`` (normalisation is inside it), or for a token policy
    the raw ``tokens`` with their masks and parents, and writes ``action``;
    ``env_class(num_robots, **env_kwargs)`` rebuilds the environment it was trained on
    (``BatchedWalkerEnv``, ``MorphologyWalkerEnv`` for ``robot=grammar``, or for ``env=gym`` the
    factory of the gymnasium task).
    """

    policy: TensorDictModuleBase
    env_kwargs: dict
    config: dict
    epoch: int
    env_class: type = BatchedWalkerEnv
    reads_tokens: bool = False  # a token policy (robot=grammar): its input is not one flat observation

    @property
    def specialist(self) -> int | None:
        """The robot a grammar specialist trained on alone (``robot.specialist``), else None."""
        return (self.config.get("robot") or {}).get("specialist")

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """Action for one flat observation (or a batch of them): the walker's or a gymnasium task's,
        in the policy's ``[-1, 1]`` box (the env it trained on, ``env_class``, clips it there and, on
        a gymnasium task, maps it onto the task's own range). A token policy's input is not one
        array: call ``.policy`` on a tensordict of its env's keys."""
        if self.reads_tokens:
            raise ValueError(f"act() takes a flat observation; this policy reads the link tokens of a "
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
    reads_tokens = policy_architecture(cfg) in TOKEN_POLICIES
    if reads_tokens:
        actor = make_token_actor(cfg, *dims)
        normalizer = make_token_norm(dims[0], loc, scale)
    else:
        actor = make_policy_actor(cfg, *dims)
        normalizer = make_observation_norm(dims[0], loc, scale)
    actor.load_state_dict(policy["actor"])
    policy = make_collecting_policy(normalizer, actor).to(device).eval()
    env_class, kwargs = env_builder(cfg)
    return LoadedPolicy(policy, kwargs, state["config"], state["epoch"], env_class, reads_tokens)
