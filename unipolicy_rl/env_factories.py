"""The env a config describes: keyword arguments of :class:`~unipolicy_rl.envs.BatchedWalkerEnv`
(``robot=vertebrate``), a :class:`~unipolicy_rl.envs.MorphologyWalkerEnv` (``robot=grammar``), or
for ``env=gym`` a gymnasium task (:func:`~unipolicy_rl.envs.gym_task.make_gym_env`).

Training, evaluation and a loaded checkpoint all build their robots from here, so a policy is
always run on the env it was trained on. One of the builders: it reads Hydra's config, so that
nothing in :mod:`unipolicy_rl.envs` does (:func:`env_kind`, :func:`gym_task` turn the ``env``
node into a checked :class:`~unipolicy_rl.envs.gym_task.GymTask`).
"""

from __future__ import annotations

import functools
import json

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import EnvBase

from unipolicy_rl.envs.batched import BatchedWalkerEnv
from unipolicy_rl.envs.gym_task import GYM, KNOWN_LEVELS, WALKER, GymTask, make_gym_env
from unipolicy_rl.envs.morphology import MorphologyWalkerEnv
from unipolicy_rl.envs.slot_layout import TOKEN_LAYOUTS, StructuralLayout
from unipolicy_rl.robots.grammar import Morphology, MorphologySplit

GRAMMAR_SIDES = ("train", "held_out", "all")
ROBOT_KINDS = ("vertebrate", "grammar")


def env_kind(cfg: DictConfig) -> str:
    """``walker`` (the default, and every config from before ``env`` existed) or ``gym``."""
    return OmegaConf.select(cfg, "env.kind", default=WALKER)


def gym_task(cfg: DictConfig) -> GymTask:
    """The config's ``env`` node as a :class:`GymTask` (its checks run)."""
    node = cfg.env
    levels = node.get("levels")
    if levels is None:
        levels = KNOWN_LEVELS.get(str(node.id).split("-")[0], (0.0,))
    return GymTask(id=str(node.id), frames_per_epoch=node.frames_per_epoch, reward=node.reward,
                   termination=node.termination, evaluation_episodes=node.evaluation_episodes,
                   levels=tuple(float(level) for level in levels))


def robot_kind(cfg: DictConfig) -> str:
    """``vertebrate`` (the thesis robot, conf/robot/vertebrate.yaml has no ``kind``) or ``grammar``."""
    return cfg.robot.get("kind", "vertebrate")


def env_kwargs(cfg: DictConfig) -> dict:
    """Keyword arguments of :class:`BatchedWalkerEnv` (all but ``num_robots``) from the config."""
    robot = cfg.robot
    if robot_kind(cfg) != "vertebrate":
        raise ValueError(f"robot kind {robot_kind(cfg)!r} is not the vertebrate BatchedWalkerEnv runs; "
                         "robot=grammar builds a MorphologyWalkerEnv (make_morphology_env)")
    return {
        "design": instantiate(cfg.design),
        "robot": instantiate(robot.settings, _convert_="all"),
        "physics": instantiate(robot.physics),
        "observation": robot.observation,
        "append_design": robot.append_design,
        "reward_weights": instantiate(robot.reward),
        "episode_length": robot.episode_length,
    }


def grammar_morphologies(cfg: DictConfig, side: str | None = None) -> tuple[MorphologySplit, tuple[Morphology, ...]]:
    """The config's split and one side of it: ``side``, by default ``robot.morphologies`` (the
    side the training env draws from). The training side is cut to its first
    ``robot.training_morphologies`` when that is set, wherever it is used (training, or the
    evaluation of the morphologies trained on). ``robot.specialist: i`` cuts the side the
    training env draws from to its morphology ``i`` alone, there and in an evaluation of that
    side: a specialist run, trained and evaluated on one robot of the split (the baseline a
    policy of many robots is measured against; ``study/morphology/report.py``)."""
    side = cfg.robot.morphologies if side is None else side
    if side not in GRAMMAR_SIDES:
        raise ValueError(f"robot.morphologies must be one of {GRAMMAR_SIDES}, got {side!r}")
    split = _split(json.dumps(OmegaConf.to_container(cfg.robot.split, resolve=True), sort_keys=True))
    count = cfg.robot.get("training_morphologies", None)
    if count is not None and not (isinstance(count, int) and not isinstance(count, bool)
                                  and 1 <= count <= len(split.train)):
        raise ValueError(f"robot.training_morphologies must be null or an integer in [1, {len(split.train)}] (the "
                         f"split's training side), got {count!r}")
    train = split.train if count is None else split.train[:count]
    chosen = {"train": train, "held_out": split.held_out, "all": train + split.held_out}[side]
    specialist = cfg.robot.get("specialist", None)
    if specialist is not None and side == cfg.robot.morphologies:
        if not (isinstance(specialist, int) and not isinstance(specialist, bool) and 0 <= specialist < len(chosen)):
            raise ValueError(f"robot.specialist must be null or an index in [0, {len(chosen) - 1}] of the "
                             f"{len(chosen)} morphologies of robot.morphologies={cfg.robot.morphologies}, "
                             f"got {specialist!r}")
        chosen = (chosen[specialist],)
    return split, chosen


@functools.lru_cache(maxsize=4)
def _split(settings: str) -> MorphologySplit:
    """The split of ``settings`` (the resolved ``robot.split`` as JSON). Drawing it builds and
    checks hundreds of robots (seconds), and the same settings always give the same split, so a
    process draws each once (validation, the probe, the collector and the evaluation share it)."""
    # Built as a partial and called here, so a bad split raises its own ValueError naming the
    # value rather than Hydra's wrapper.
    return instantiate(OmegaConf.create(json.loads(settings)), _convert_="all", _partial_=True)()


def morphology_env_kwargs(cfg: DictConfig, side: str | None = None) -> dict:
    """Keyword arguments of :class:`MorphologyWalkerEnv` (all but ``num_robots``) for the
    morphologies of ``side`` (default ``robot.morphologies``). Unset ``max_links`` pads to the
    most links any robot of the split's size limits may have, so held-out robots fit the same
    tokens (and a padded-MLP policy, whose weights are tied to the padding, runs on every side).
    ``robot.token_layout: structural`` fixes each link's slot by its role, with room for every
    robot of the split's size limits (:class:`StructuralLayout`); ``packed`` (the default) fills
    the first slots in link order."""
    if robot_kind(cfg) != "grammar":
        raise ValueError(f"a MorphologyWalkerEnv needs robot=grammar, got robot kind {robot_kind(cfg)!r}")
    robot = cfg.robot
    _, morphologies = grammar_morphologies(cfg, side)
    limits = instantiate(robot.split.train_limits, _convert_="all"), instantiate(robot.split.held_out_limits,
                                                                                 _convert_="all")
    max_links = robot.max_links if robot.max_links is not None else max(limit.max_links for limit in limits)
    layout = robot.token_layout
    if layout not in TOKEN_LAYOUTS:
        raise ValueError(f"robot.token_layout must be one of {TOKEN_LAYOUTS}, got {layout!r}")
    if robot.max_links is not None and layout == "packed":  # (a structural layout's slots: the env checks them)
        largest = max(morphology.num_links for morphology in morphologies)
        if largest > max_links:
            raise ValueError(f"robot.max_links={max_links} token slots are fewer than the {largest} links of the "
                             f"largest robot of the morphologies {side or robot.morphologies!r}: raise "
                             f"robot.max_links to {largest} or more, or set it null (room for all)")
    return {
        "morphologies": morphologies,
        "max_links": max_links,
        "design": instantiate(cfg.design),
        "physics": instantiate(robot.physics),
        "reward_weights": instantiate(robot.reward),
        "episode_length": robot.episode_length,
        "sampling": robot.sampling,
        "driven_joints": None if robot.driven_joints is None else tuple(robot.driven_joints),
        "design_in_tokens": robot.design_in_tokens,
        "token_layout": StructuralLayout.covering(limits) if layout == "structural" else None,
        "clock_frequency": robot.get("clock_frequency"),
    }


def make_morphology_env(cfg: DictConfig, num_robots: int) -> MorphologyWalkerEnv:
    """The ``robot=grammar`` env of ``num_robots`` robots (:func:`morphology_env_kwargs`)."""
    return MorphologyWalkerEnv(num_robots, **morphology_env_kwargs(cfg))


def frames_per_epoch(cfg: DictConfig) -> int:
    """Real env steps of one epoch: ``episodes_per_epoch`` walker episodes of ``robot.episode_length``
    steps, or a gym task's ``env.frames_per_epoch``."""
    if env_kind(cfg) == GYM:
        return int(cfg.env.frames_per_epoch)
    return cfg.episodes_per_epoch * cfg.robot.episode_length


def steps_per_env_epoch(cfg: DictConfig) -> int:
    """Steps each env takes in one epoch: a walker robot's ``robot.episode_length``, or the gym
    task's one env's ``env.frames_per_epoch``."""
    return int(cfg.env.frames_per_epoch) if env_kind(cfg) == GYM else int(cfg.robot.episode_length)


def episode_length(cfg: DictConfig) -> int:
    """The longest episode: the walker's ``robot.episode_length``, or a gym task's time limit."""
    return gym_task(cfg).episode_length if env_kind(cfg) == GYM else cfg.robot.episode_length


def env_builder(cfg: DictConfig) -> tuple[type[EnvBase], dict]:
    """The env class the config's robot runs in and its keyword arguments (all but ``num_robots``):
    :class:`BatchedWalkerEnv` and :func:`env_kwargs` for ``robot=vertebrate``,
    :class:`MorphologyWalkerEnv` and :func:`morphology_env_kwargs` for ``robot=grammar``, and
    :func:`make_gym_env` with the task's id for ``env=gym``. All are plain picklable values, so
    collector worker processes and Ray actors build the same env."""
    if env_kind(cfg) == GYM:
        return make_gym_env, {"env_id": gym_task(cfg).id}
    kind = robot_kind(cfg)
    if kind not in ROBOT_KINDS:
        raise ValueError(f"robot.kind must be one of {ROBOT_KINDS}, got {kind!r}")
    if kind == "grammar":
        return MorphologyWalkerEnv, morphology_env_kwargs(cfg)
    return BatchedWalkerEnv, env_kwargs(cfg)
