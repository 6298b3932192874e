"""``BatchedWalkerEnv``: many robots per TorchRL step, one PyBullet client each, in one process.

TorchRL's per-step overhead is roughly flat in the batch size, so stepping N robots per
call keeps a process near raw physics speed; wrap it in ``ParallelEnv`` to use more cores.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from unipolicy_rl.envs.design import Design, DesignDistribution
from unipolicy_rl.envs.reward import RewardWeights, walking_reward
from unipolicy_rl.envs.simulation import (
    PhysicsSettings,
    RobotSettings,
    WalkerSimulation,
    healthy_rows,
    joint_targets,
    observation_columns,
)


def numpy_tensordict(arrays: dict[str, np.ndarray], batch_size: torch.Size, device: torch.device) -> TensorDict:
    """An env step's numpy arrays as a TensorDict, wrapped without a copy on the CPU (the arrays
    must be fresh: the env's own buffers change in place on later steps)."""
    tensors = {key: torch.from_numpy(value) for key, value in arrays.items()}
    if device.type != "cpu":
        tensors = {key: value.to(device) for key, value in tensors.items()}
    return TensorDict(tensors, batch_size=batch_size, device=device)


class BatchedWalkerEnv(EnvBase):
    """``num_robots`` independent walkers with batch_size ``[num_robots]``.

    Keys: ``observation`` (float32), ``design`` (l, rho of each robot's current build),
    ``physics_fault`` (the step blew up and was truncated), plus TorchRL's reward and
    done/terminated/truncated; with ``full_state`` also ``state``, the ``full`` layout
    (every link and the actuated joints), of which ``observation`` is then a column
    selection: what a world model learns from when the policy sees less. Episodes are
    truncated after ``episode_length`` steps, or
    never with ``None`` (the caller ends them, as training's collector does), and
    early on a physics fault, which repeats the robot's last good observation. Partial
    resets (``_reset`` mask) rebuild only the masked robots; an explicit ``design`` in the
    reset tensordict overrides the distribution for those robots (used by evaluation).
    Same seed, same trajectories.
    """

    batch_locked = True

    def __init__(
        self,
        num_robots: int = 8,
        design: DesignDistribution | None = None,
        robot: RobotSettings | None = None,
        physics: PhysicsSettings | None = None,
        observation: str = "thesis",
        append_design: bool = False,
        reward_weights: RewardWeights | None = None,
        episode_length: int | None = 100,
        device: str | torch.device = "cpu",
        full_state: bool = False,
    ):
        if not (isinstance(num_robots, (int, np.integer)) and num_robots >= 1):
            raise ValueError(f"num_robots must be a positive integer, got {num_robots!r}")
        if episode_length is not None and not (isinstance(episode_length, (int, np.integer)) and episode_length >= 1):
            raise ValueError(f"episode_length must be a positive integer or None, got {episode_length!r}")
        super().__init__(batch_size=torch.Size([num_robots]), device=device)
        self.design_distribution = design or DesignDistribution()
        self.reward_weights = reward_weights or RewardWeights()
        self.episode_length = None if episode_length is None else int(episode_length)
        self.append_design = append_design
        robot, physics = robot or RobotSettings(), physics or PhysicsSettings()
        self.full_state = full_state
        # With full_state the robots read the full layout and the observation is a column view of it.
        read = "full" if full_state else observation
        self.simulations = [WalkerSimulation(robot, physics, read) for _ in range(num_robots)]
        self._observation_columns = observation_columns(robot, observation) if full_state else None
        self._action_range = physics.action_range
        self._rng = np.random.default_rng()
        self._steps = np.zeros(num_robots, dtype=np.int64)
        raw_size = self.simulations[0].observation_size
        self._raw = np.zeros((num_robots, raw_size))
        # Per robot: what turns its world-frame state into its observation, and its last
        # healthy observation; kept here as arrays so a step handles the batch at once
        # (a simulation's own last_observation belongs to its step(), which is not used here).
        self._start_offsets = np.zeros((num_robots, raw_size))
        self._last_good = np.zeros((num_robots, raw_size))
        self._designs = np.zeros((num_robots, 2))
        self._faults = np.zeros(num_robots, dtype=bool)
        self._all_robots = np.ones(num_robots, dtype=bool)
        observation_size = raw_size if self._observation_columns is None else len(self._observation_columns)
        self._make_specs(observation_size + (2 if append_design else 0), self.simulations[0].num_actions,
                         raw_size if full_state else None)

    def _make_specs(self, observation_size: int, num_actions: int, state_size: int | None) -> None:
        shape = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded((*shape, observation_size), dtype=torch.float32, device=self.device),
            design=Unbounded((*shape, 2), dtype=torch.float32, device=self.device),
            physics_fault=Categorical(2, (*shape, 1), dtype=torch.bool, device=self.device),
            shape=shape,
        )
        if state_size is not None:
            self.observation_spec["state"] = Unbounded((*shape, state_size), dtype=torch.float32, device=self.device)
        self.action_spec = Bounded(-1.0, 1.0, (*shape, num_actions), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded((*shape, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(2, (*shape, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=shape)

    @property
    def control_period(self) -> float:
        return self.simulations[0].physics.control_period

    def _output(self, reward: np.ndarray | None = None, done: np.ndarray | None = None) -> TensorDict:
        # Every entry is built in numpy and wrapped by torch.from_numpy without a copy:
        # right after 32 robots' physics, torch's own conversions run from cold caches and
        # cost more than numpy's.
        n = self.batch_size[0]
        raw = self._raw if self._observation_columns is None else self._raw[:, self._observation_columns]
        observation = np.concatenate([raw, self._designs], axis=1) if self.append_design else raw
        # Copies, never views: the flags array changes in place on later steps and resets,
        # and ``done`` may be that array.
        done = np.zeros((n, 1), dtype=bool) if done is None else done.reshape(n, 1).copy()
        out = {
            "observation": observation.astype(np.float32),
            "design": self._designs.astype(np.float32),
            "physics_fault": self._faults.reshape(n, 1).copy(),
            "done": done,
            "terminated": np.zeros_like(done),
            "truncated": done.copy(),
        }
        if self.full_state:
            out["state"] = self._raw.astype(np.float32)
        if reward is not None:
            out["reward"] = reward.astype(np.float32).reshape(n, 1)
        return numpy_tensordict(out, self.batch_size, self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n = self.batch_size[0]
        mask = np.ones(n, dtype=bool)
        explicit = None
        if tensordict is not None:
            if "_reset" in tensordict.keys():
                mask = tensordict.get("_reset").reshape(n).cpu().numpy()
            if "design" in tensordict.keys():
                explicit = tensordict.get("design").reshape(n, 2).cpu().double().numpy()
        for i in np.flatnonzero(mask):
            design = Design(*explicit[i]) if explicit is not None else self.design_distribution.sample(self._rng)
            self._raw[i] = self._last_good[i] = self.simulations[i].reset(design)
            self._start_offsets[i] = self.simulations[i].start_offset
            self._designs[i] = (design.length, design.density)
            self._steps[i] = 0
            self._faults[i] = False
        return self._output()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Vectorised over the batch: target mapping and fault checks cost once per call,
        # leaving the per-robot loop to PyBullet itself. TorchRL's partial steps ("_step"
        # mask) advance only the masked robots; the others keep their state, step count and
        # flags, and get zero reward.
        n = self.batch_size[0]
        stepping = tensordict.get("_step", None)
        stepping = self._all_robots if stepping is None else stepping.reshape(n).cpu().numpy()
        targets = joint_targets(tensordict.get("action").detach().cpu().numpy(), self._action_range).tolist()
        active = np.flatnonzero(stepping)
        states = []
        for i in active:  # read each robot right after its physics, while its world is in cache
            simulation = self.simulations[i]
            simulation.advance(targets[i])
            states.append(simulation.world_state())
        if len(active) == n:
            np.subtract(states, self._start_offsets, out=self._raw)
        elif states:
            self._raw[active] = np.subtract(states, self._start_offsets[active])
        good = stepping & healthy_rows(self._raw)
        if good.all():  # the usual step: every robot stepped and none blew up
            np.copyto(self._last_good, self._raw)
            reward = walking_reward(self._raw, self.reward_weights)
        else:
            faulted = stepping & ~good
            self._faults |= faulted
            self._last_good[good] = self._raw[good]
            self._raw[faulted] = self._last_good[faulted]  # so no NaN leaves the env
            reward = np.where(stepping, walking_reward(self._raw, self.reward_weights), 0.0)
        self._steps += stepping
        done = self._faults if self.episode_length is None else self._faults | (self._steps >= self.episode_length)
        return self._output(reward, done)

    def _set_seed(self, seed: int | None) -> None:
        self._rng = np.random.default_rng(seed)

    def close(self, *, raise_if_closed: bool = True) -> None:
        for simulation in self.simulations:
            simulation.close()
        super().close(raise_if_closed=raise_if_closed)
