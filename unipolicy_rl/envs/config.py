"""The env a config describes: keyword arguments of :class:`~unipolicy_rl.envs.BatchedWalkerEnv`
(``robot=vertebrate``), or a :class:`~unipolicy_rl.envs.MorphologyWalkerEnv` (``robot=grammar``).

Training, evaluation and a loaded checkpoint all build their robots from here, so a policy is
always run on the env it was trained on.
"""

from __future__ import annotations

from hydra.utils import instantiate
from omegaconf import DictConfig

from unipolicy_rl.envs.morphology import MorphologyWalkerEnv
from unipolicy_rl.robots.grammar import Morphology, MorphologySplit

GRAMMAR_SIDES = ("train", "held_out", "all")


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


def grammar_morphologies(cfg: DictConfig) -> tuple[MorphologySplit, tuple[Morphology, ...]]:
    """The config's split and the side of it (``robot.morphologies``) the env draws from."""
    side = cfg.robot.morphologies
    if side not in GRAMMAR_SIDES:
        raise ValueError(f"robot.morphologies must be one of {GRAMMAR_SIDES}, got {side!r}")
    # Built as a partial and called here, so a bad split raises its own ValueError naming the
    # value rather than Hydra's wrapper.
    split = instantiate(cfg.robot.split, _convert_="all", _partial_=True)()
    chosen = {"train": split.train, "held_out": split.held_out, "all": split.train + split.held_out}[side]
    return split, chosen


def make_morphology_env(cfg: DictConfig, num_robots: int) -> MorphologyWalkerEnv:
    """The ``robot=grammar`` env of ``num_robots`` robots. Unset ``max_links`` pads to the most
    links any robot of the split's size limits may have, so held-out robots fit the same tokens."""
    if robot_kind(cfg) != "grammar":
        raise ValueError(f"make_morphology_env needs robot=grammar, got robot kind {robot_kind(cfg)!r}")
    robot = cfg.robot
    split, morphologies = grammar_morphologies(cfg)
    limits = instantiate(robot.split.train_limits, _convert_="all"), instantiate(robot.split.held_out_limits,
                                                                                 _convert_="all")
    max_links = robot.max_links if robot.max_links is not None else max(limit.max_links for limit in limits)
    return MorphologyWalkerEnv(
        num_robots,
        morphologies,
        max_links=max_links,
        design=instantiate(cfg.design),
        physics=instantiate(robot.physics),
        reward_weights=instantiate(robot.reward),
        episode_length=robot.episode_length,
        sampling=robot.sampling,
        driven_joints=None if robot.driven_joints is None else tuple(robot.driven_joints),
        design_in_tokens=robot.design_in_tokens,
    )
