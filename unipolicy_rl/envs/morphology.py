"""``MorphologyWalkerEnv``: robots of different grammar morphologies side by side in one TorchRL env.

Each robot of the batch draws a morphology from the env's set and a design (l, rho) per episode,
and is observed as link tokens padded to ``max_links`` (the keys and features of
:mod:`unipolicy_rl.envs.tokens`). Physics, motors, fault handling and the reward are those of
:class:`~unipolicy_rl.envs.BatchedWalkerEnv`: the same world building and PD motors, the same
explosion check, the same walking reward read off the root token; the grammar's thesis robot
(``VERTEBRATE`` with its hips driven) walks exactly as the vertebrate env's robot does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from unipolicy_rl.envs.batched import numpy_tensordict
from unipolicy_rl.envs.design import SE_LENGTH_RANGE, Design, DesignDistribution
from unipolicy_rl.envs.link_tokens import BUILT, LINK_STATE_SIZE, MOVING, RobotTokens, moving_features, robot_tokens
from unipolicy_rl.envs.morphology_simulation import MorphologySimulation
from unipolicy_rl.envs.reward import RewardWeights, walking_reward
from unipolicy_rl.envs.simulation import PhysicsSettings, healthy_rows, joint_targets
from unipolicy_rl.envs.slot_layout import StructuralLayout, packed_slots
from unipolicy_rl.envs.tokens import ACTION_MASK, CLOCK, MORPHOLOGY, TOKEN_MASK, TOKEN_PARENT, TOKEN_SIZE, TOKENS
from unipolicy_rl.robots import RobotDescription
from unipolicy_rl.robots.grammar import RULES, Morphology, PartKinds, derive, describe, part_kinds, split_morphologies
from unipolicy_rl.robots.grammar.derivation import RobotGraph

# How a robot's morphology is drawn at each reset: independently and uniformly, or "balanced":
# through the set in shuffled rounds, each morphology once per round, so every one gets an equal
# share of episodes however few are drawn.
SAMPLINGS = ("uniform", "balanced")
# The joint types a grammar robot's hinges have (RoboGrammar's rule set and the thesis hip).
HINGE_TYPES = tuple(sorted({edge.joint.name for rule in RULES.values() for edge in rule.right_edges
                            if edge.joint is not None and edge.joint.kind == "hinge"}))


@dataclass(frozen=True, eq=False)
class _Morph:
    """What the env keeps of one morphology of its set: its derived graph, its parts' kinds, the
    hinges it drives, the robot at the design the tokens report sizes of, and the token slot of
    each of its links (:mod:`unipolicy_rl.envs.slot_layout`)."""

    graph: RobotGraph
    kinds: PartKinds
    driven: tuple[str, ...]
    nominal: RobotDescription
    slots: np.ndarray

    def describe(self, design: Design) -> RobotDescription:
        return describe(self.graph, design.length, design.density, actuated=self.driven)


def default_morphologies() -> tuple[Morphology, ...]:
    """The training side of the default split (seed 0, robots standing over the SE length range)."""
    return split_morphologies(0, SE_LENGTH_RANGE).train


class MorphologyWalkerEnv(EnvBase):
    """``num_robots`` walkers of the grammar with batch_size ``[num_robots]``, one PyBullet client each.

    Keys: ``tokens``, ``token_mask``, ``token_parent``, ``action_mask`` and ``morphology`` (see
    :mod:`unipolicy_rl.envs.tokens`), ``design`` (l, rho of each robot's build), ``physics_fault``,
    plus TorchRL's reward and done/terminated/truncated. The action is ``[num_robots, max_links]``
    in [-1, 1]: slot i drives the parent joint of the link at slot i where ``action_mask`` is True
    and is ignored elsewhere. Episodes are truncated after ``episode_length`` steps (never with None) and early on
    a physics fault, which repeats the robot's last good tokens. A reset draws each robot's
    morphology (``sampling``) and design; a ``morphology`` or ``design`` in the reset tensordict
    forces them for the robots reset (evaluation). Partial resets and steps (``_reset``, ``_step``)
    touch only the masked robots. Same seed, same trajectories.

    ``driven_joints``: the hinge types the policy drives (e.g. ``("axial_roll",)``), the others
    locked; None drives every hinge, as RoboGrammar. ``design_in_tokens``: tokens give each link's
    size at the episode's design instead of at the design distribution's mean. ``token_layout``:
    None packs each robot's links into the first slots in link order; a
    :class:`~unipolicy_rl.envs.slot_layout.StructuralLayout` puts each link at the slot its role
    in the body fixes, padding in the gaps (the masks and ``token_parent`` follow the slots).
    ``clock_frequency``: adds ``clock``, the ``(sin, cos)`` of each robot's gait phase at this many
    Hz from its episode's start (:data:`~unipolicy_rl.envs.tokens.CLOCK`); None: no clock.
    """

    batch_locked = True

    def __init__(
        self,
        num_robots: int = 8,
        morphologies: Sequence[Morphology] | None = None,
        max_links: int | None = None,
        design: DesignDistribution | None = None,
        physics: PhysicsSettings | None = None,
        reward_weights: RewardWeights | None = None,
        episode_length: int | None = 100,
        sampling: str = "uniform",
        driven_joints: Sequence[str] | None = None,
        design_in_tokens: bool = False,
        token_layout: StructuralLayout | None = None,
        clock_frequency: float | None = None,
        device: str | torch.device = "cpu",
    ):
        if not (isinstance(num_robots, (int, np.integer)) and num_robots >= 1):
            raise ValueError(f"num_robots must be a positive integer, got {num_robots!r}")
        if episode_length is not None and not (isinstance(episode_length, (int, np.integer)) and episode_length >= 1):
            raise ValueError(f"episode_length must be a positive integer or None, got {episode_length!r}")
        if sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
        morphologies = default_morphologies() if morphologies is None else tuple(morphologies)
        if not morphologies:
            raise ValueError("the morphology set is empty: give at least one morphology (an empty split side?)")
        for index, morphology in enumerate(morphologies):
            if not isinstance(morphology, Morphology):
                raise ValueError(f"morphology {index} is not a Morphology: {morphology!r}")
        if driven_joints is not None:
            driven_joints = tuple(driven_joints)
            unknown = sorted(set(driven_joints) - set(HINGE_TYPES))
            if unknown or not driven_joints:
                raise ValueError(f"driven_joints must name hinge types {list(HINGE_TYPES)}, got {list(driven_joints)}")
        if token_layout is not None and not isinstance(token_layout, StructuralLayout):
            raise ValueError(f"token_layout must be None (packed) or a StructuralLayout, got {token_layout!r}")
        if clock_frequency is not None and not (isinstance(clock_frequency, (int, float, np.number))
                                                and 0 < clock_frequency < float("inf")):
            raise ValueError(f"clock_frequency must be a positive number of Hz or None, got {clock_frequency!r}")
        if max_links is not None and not (isinstance(max_links, (int, np.integer)) and max_links >= 1):
            raise ValueError(f"max_links must be a positive integer or None, got {max_links!r}")
        super().__init__(batch_size=torch.Size([num_robots]), device=device)
        self.morphologies = morphologies
        self.token_layout = token_layout
        self.design_distribution = design or DesignDistribution()
        self.physics = physics or PhysicsSettings()
        self.reward_weights = reward_weights or RewardWeights()
        self.episode_length = None if episode_length is None else int(episode_length)
        self.sampling = sampling
        self.design_in_tokens = design_in_tokens
        self.clock_frequency = None if clock_frequency is None else float(clock_frequency)
        self._morphs = [self._prepare(index, morphology, driven_joints)
                        for index, morphology in enumerate(morphologies)]
        needed = max(int(morph.slots.max()) + 1 for morph in self._morphs)
        self.max_links = needed if max_links is None else int(max_links)
        for index, (morphology, morph) in enumerate(zip(morphologies, self._morphs, strict=True)):
            if morph.slots.max() >= self.max_links:
                what = (f"has {morphology.num_links} links" if token_layout is None
                        else f"puts a link at slot {int(morph.slots.max())} of the structural layout")
                raise ValueError(f"morphology {index} {what}, more than max_links={self.max_links} token slots: "
                                 f"raise max_links ({morphology.derivation()})")
        self.simulations = [MorphologySimulation(self.physics) for _ in range(num_robots)]

        n, links = num_robots, self.max_links
        self._rng = np.random.default_rng()
        self._deck: list[int] = []
        self._robots: list[RobotTokens | None] = [None] * n
        self._slots: list[np.ndarray] = [packed_slots(0)] * n  # each robot's link -> slot
        self._driven_slots: list[np.ndarray] = [packed_slots(0)] * n  # its motors' slots, in motor order
        self._link_states = np.zeros((n, links, LINK_STATE_SIZE))
        self._joints = np.zeros((n, links, 2))
        self._start_xy = np.zeros((n, 2))
        self._base_inertial_rotations = np.repeat(np.eye(3)[None], n, axis=0)
        self._built = np.zeros((n, links, BUILT.stop - BUILT.start))
        self._token_mask = np.zeros((n, links), dtype=bool)
        self._parents = np.full((n, links), -1, dtype=np.int64)
        self._action_mask = np.zeros((n, links), dtype=bool)
        self._tokens = np.zeros((n, links, TOKEN_SIZE))
        self._last_good = np.zeros((n, links, TOKEN_SIZE))
        self._morphology = np.zeros(n, dtype=np.int64)
        self._designs = np.zeros((n, 2))
        self._steps = np.zeros(n, dtype=np.int64)
        self._faults = np.zeros(n, dtype=bool)
        self._all_robots = np.ones(n, dtype=bool)
        self._make_specs()

    def _prepare(self, index: int, morphology: Morphology, driven_types: tuple[str, ...] | None) -> _Morph:
        graph = derive(morphology.derivation())
        kinds = part_kinds(graph)
        every = describe(graph)
        driven = tuple(joint.name for joint, joint_type in zip(every.joints, kinds.joints, strict=True)
                       if joint.kind == "hinge" and (driven_types is None or joint_type in driven_types))
        if not driven:
            raise ValueError(f"morphology {index} has no hinge of the driven types {list(driven_types)}: "
                             f"its joints are {sorted(set(kinds.joints))} ({morphology.derivation()})")
        mean = self.design_distribution.mean
        try:
            slots = (packed_slots(len(every.links)) if self.token_layout is None
                     else self.token_layout.slots([link.name for link in every.links]))
        except ValueError as error:
            raise ValueError(f"morphology {index} does not fit the token layout: {error} "
                             f"({morphology.derivation()})") from None
        return _Morph(graph, kinds, driven, describe(graph, mean.length, mean.density, actuated=driven), slots)

    def _make_specs(self) -> None:
        shape, links, device = self.batch_size, self.max_links, self.device
        self.observation_spec = Composite(
            {
                TOKENS: Unbounded((*shape, links, TOKEN_SIZE), dtype=torch.float32, device=device),
                TOKEN_MASK: Binary(links, (*shape, links), dtype=torch.bool, device=device),
                TOKEN_PARENT: Bounded(-1, links - 1, (*shape, links), dtype=torch.int64, device=device),
                ACTION_MASK: Binary(links, (*shape, links), dtype=torch.bool, device=device),
                MORPHOLOGY: Categorical(len(self.morphologies), (*shape, 1), dtype=torch.int64, device=device),
                "design": Unbounded((*shape, 2), dtype=torch.float32, device=device),
                "physics_fault": Categorical(2, (*shape, 1), dtype=torch.bool, device=device),
            },
            shape=shape,
        )
        if self.clock_frequency is not None:
            self.observation_spec[CLOCK] = Bounded(-1.0, 1.0, (*shape, 2), dtype=torch.float32, device=device)
        self.action_spec = Bounded(-1.0, 1.0, (*shape, links), dtype=torch.float32, device=device)
        self.reward_spec = Unbounded((*shape, 1), dtype=torch.float32, device=device)
        flag = Categorical(2, (*shape, 1), dtype=torch.bool, device=device)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=shape)

    @property
    def control_period(self) -> float:
        return self.physics.control_period

    # -- drawing robots ------------------------------------------------------------
    def _draw_morphology(self) -> int:
        if self.sampling == "uniform":
            return int(self._rng.integers(len(self.morphologies)))
        if not self._deck:
            self._deck = self._rng.permutation(len(self.morphologies)).tolist()
        return self._deck.pop()

    def _forced(self, tensordict: TensorDictBase | None, key: str, width: int) -> np.ndarray | None:
        if tensordict is None or key not in tensordict.keys():
            return None
        return tensordict.get(key).reshape(self.batch_size[0], width).cpu().numpy()

    # -- TorchRL -------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n = self.batch_size[0]
        mask = np.ones(n, dtype=bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(n).cpu().numpy()
        forced_morphology = self._forced(tensordict, MORPHOLOGY, 1)
        forced_design = self._forced(tensordict, "design", 2)
        rows = np.flatnonzero(mask)
        if forced_morphology is not None:
            for i in rows:
                index = forced_morphology[i, 0]
                if not 0 <= index < len(self.morphologies):
                    raise ValueError(f"unknown morphology index {int(index)} for robot {i}; the env's set has "
                                     f"{len(self.morphologies)} morphologies (0 to {len(self.morphologies) - 1})")
        for i in rows:
            index = int(forced_morphology[i, 0]) if forced_morphology is not None else self._draw_morphology()
            design = (Design(*forced_design[i].astype(float)) if forced_design is not None
                      else self.design_distribution.sample(self._rng))
            self._build(i, index, design)
        self._compose(rows)
        self._last_good[rows] = self._tokens[rows]
        return self._output()

    def _build(self, i: int, index: int, design: Design) -> None:
        morph = self._morphs[index]
        description = morph.describe(design)
        self._start_xy[i] = self.simulations[i].build(description)
        self._base_inertial_rotations[i] = self.simulations[i].base_inertial_rotation
        robot = robot_tokens(description, morph.kinds.links, description if self.design_in_tokens else morph.nominal)
        slots = morph.slots
        self._robots[i] = robot
        self._slots[i] = slots
        self._driven_slots[i] = slots[robot.driven_links]
        self._token_mask[i] = False
        self._token_mask[i, slots] = True
        self._parents[i] = -1
        self._parents[i, slots] = np.where(robot.parents >= 0, slots[robot.parents], -1)
        self._action_mask[i] = False
        self._action_mask[i, slots] = robot.action_mask
        self._built[i] = 0.0
        self._built[i, slots] = robot.built
        self._link_states[i] = 0.0
        self._joints[i] = 0.0
        self._read(i)
        self._morphology[i] = index
        self._designs[i] = (design.length, design.density)
        self._steps[i] = 0
        self._faults[i] = False

    def _read(self, i: int) -> None:
        robot = self._robots[i]
        states, joints = self.simulations[i].read()
        self._link_states[i, self._slots[i]] = np.reshape(states, (robot.num_links, LINK_STATE_SIZE))
        self._joints[i, self._driven_slots[i]] = np.reshape(joints, (-1, 2))

    def _compose(self, rows: np.ndarray) -> None:
        """The tokens of robots ``rows`` from their last read state; padding exactly zero."""
        tokens = np.empty((len(rows), self.max_links, TOKEN_SIZE))
        tokens[..., MOVING] = moving_features(self._link_states[rows], self._joints[rows], self._start_xy[rows],
                                                 self._base_inertial_rotations[rows])
        tokens[..., BUILT] = self._built[rows]
        tokens[~self._token_mask[rows]] = 0.0
        self._tokens[rows] = tokens

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        # As BatchedWalkerEnv: targets and fault checks vectorised over the batch, the per-robot
        # loop left to PyBullet; partial steps advance only the masked robots.
        n = self.batch_size[0]
        stepping = tensordict.get("_step", None)
        stepping = self._all_robots if stepping is None else stepping.reshape(n).cpu().numpy()
        action = tensordict.get("action").detach().cpu().numpy()
        # Masked slots count for nothing, whatever they hold (NaN included).
        targets = joint_targets(np.where(self._action_mask, action, 0.0), self.physics.action_range)
        active = np.flatnonzero(stepping)
        for i in active:  # read each robot right after its physics, while its world is in cache
            self.simulations[i].advance(targets[i, self._driven_slots[i]].tolist())
            self._read(i)
        self._compose(active)
        good = stepping & healthy_rows(self._tokens.reshape(n, -1))
        faulted = stepping & ~good
        self._last_good[good] = self._tokens[good]
        if faulted.any():
            self._faults |= faulted
            self._tokens[faulted] = self._last_good[faulted]  # so no NaN leaves the env
        reward = np.where(stepping, walking_reward(self._tokens[:, 0, :], self.reward_weights), 0.0)
        self._steps += stepping
        done = self._faults if self.episode_length is None else self._faults | (self._steps >= self.episode_length)
        return self._output(reward, done)

    def _output(self, reward: np.ndarray | None = None, done: np.ndarray | None = None) -> TensorDict:
        n = self.batch_size[0]
        # Copies, never views: these arrays change in place on later steps and resets.
        done = np.zeros((n, 1), dtype=bool) if done is None else done.reshape(n, 1).copy()
        out = {
            TOKENS: self._tokens.astype(np.float32),
            TOKEN_MASK: self._token_mask.copy(),
            TOKEN_PARENT: self._parents.copy(),
            ACTION_MASK: self._action_mask.copy(),
            MORPHOLOGY: self._morphology.reshape(n, 1).copy(),
            "design": self._designs.astype(np.float32),
            "physics_fault": self._faults.reshape(n, 1).copy(),
            "done": done,
            "terminated": np.zeros_like(done),
            "truncated": done.copy(),
        }
        if self.clock_frequency is not None:
            phase = 2 * np.pi * self.clock_frequency * self.control_period * self._steps
            out[CLOCK] = np.stack([np.sin(phase), np.cos(phase)], -1).astype(np.float32)
        if reward is not None:
            out["reward"] = reward.astype(np.float32).reshape(n, 1)
        return numpy_tensordict(out, self.batch_size, self.device)

    def _set_seed(self, seed: int | None) -> None:
        self._rng = np.random.default_rng(seed)
        self._deck = []

    def close(self, *, raise_if_closed: bool = True) -> None:
        for simulation in self.simulations:
            simulation.close()
        super().close(raise_if_closed=raise_if_closed)
