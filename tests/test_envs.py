"""WalkerEnv (gymnasium) and BatchedWalkerEnv (TorchRL): checkers, determinism, faults, bad input."""

import functools
import multiprocessing
import threading
import time

import gymnasium
import numpy as np
import pybullet
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDict
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.cpu_speed.parallel_env import SleepingParallelEnv, WakingDoneFlags
from unipolicy_rl.envs import (
    ENV_ID,
    BatchedWalkerEnv,
    Design,
    DesignDistribution,
    PhysicsSettings,
    RewardWeights,
    RobotSettings,
    WalkerEnv,
    walking_reward,
)
from unipolicy_rl.envs.gait import SineGait, walk


def test_gymnasium_checker_passes():
    env = gymnasium.make(ENV_ID)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("kwargs", [{}, {"observation": "full", "append_design": True}])
def test_torchrl_spec_checker_passes(kwargs):
    env = BatchedWalkerEnv(3, **kwargs)
    env.set_seed(0)
    check_env_specs(env)
    env.close()


def test_observation_sizes():
    assert WalkerEnv().observation_space.shape == (18,)
    assert WalkerEnv(append_design=True).observation_space.shape == (20,)
    assert WalkerEnv(observation="full").observation_space.shape == (15 * 6 + 2 * 4,)


def _gym_trajectory(seed):
    env = WalkerEnv()
    observation, info = env.reset(seed=seed)
    observations, rng = [observation], np.random.default_rng(1)
    for _ in range(20):
        observations.append(env.step(rng.uniform(-1, 1, 4))[0])
    env.close()
    return info["design"], np.array(observations)


def test_gym_env_is_deterministic_under_a_seed():
    design_a, a = _gym_trajectory(7)
    design_b, b = _gym_trajectory(7)
    design_c, _ = _gym_trajectory(8)
    assert design_a == design_b != design_c
    np.testing.assert_array_equal(a, b)


def test_batched_env_is_deterministic_under_a_seed():
    def rollout(seed):
        env = BatchedWalkerEnv(3)
        env.set_seed(seed)
        torch.manual_seed(0)
        data = env.rollout(15)
        env.close()
        return data

    a, b = rollout(3), rollout(3)
    torch.testing.assert_close(a["next", "observation"], b["next", "observation"], rtol=0, atol=0)
    assert not torch.equal(a["design"], rollout(4)["design"])


def test_reward_is_the_thesis_formula():
    weights = RewardWeights(w_x=2.0, w_y=-0.5, w_x_dot=3.0)
    env = WalkerEnv(reward_weights=weights)
    env.reset(seed=0)
    for _ in range(10):
        observation, reward, *_ = env.step(np.full(4, 0.7))
        expected = 2.0 * observation[0] - 0.5 * abs(observation[1]) + 3.0 * observation[3]
        assert reward == pytest.approx(expected, abs=1e-5)
    env.close()
    batch = torch.tensor([[1.0, -2.0, 0.3, 0.5] + [0.0] * 14])
    assert walking_reward(batch, weights).item() == pytest.approx(2.0 - 1.0 + 1.5)


def test_episode_truncates_after_episode_length_and_reports_metrics():
    env = WalkerEnv(design=DesignDistribution.fixed(0.175, 0.5), episode_length=5)
    env.reset(seed=0)
    for step in range(5):
        _, _, terminated, truncated, info = env.step(np.zeros(4))
        assert not terminated and truncated == (step == 4)
    assert info["design"] == Design(0.175, 0.5)
    assert info["mean_forward_speed"] == pytest.approx(info["forward_displacement"] / (5 * 16 / 240))
    env.close()


@pytest.mark.parametrize(("episode_length", "first_done"), [(3, 3), (None, None)])
def test_batched_env_time_limit_or_none(episode_length, first_done):
    env = BatchedWalkerEnv(2, DesignDistribution.fixed(0.175, 0.5), episode_length=episode_length)
    env.set_seed(0)
    done = env.rollout(6, break_when_any_done=False)["next", "done"].squeeze(-1)  # [robots, time]
    steps_done = [step + 1 for step in range(6) if done[:, step].all()]
    assert (steps_done[0] if steps_done else None) == first_done
    assert not done.any() if episode_length is None else done[:, 2].all()
    env.close()


def test_explicit_design_in_reset_options():
    env = WalkerEnv()
    _, info = env.reset(seed=0, options={"design": (0.16, 0.55)})
    assert info["design"] == Design(0.16, 0.55)
    env.close()


def test_exploding_physics_truncates_with_a_flag_and_no_nan():
    env = WalkerEnv()
    previous, _ = env.reset(seed=0)
    simulation = env.simulation
    # Throw the robot far past any physical state; the fault check must catch it.
    pybullet.resetBasePositionAndOrientation(simulation.body.body_id, (1e4, 0, 1), (0, 0, 0, 1),
                                             physicsClientId=simulation.client)
    observation, reward, _, truncated, info = env.step(np.zeros(4))
    assert truncated and info["physics_fault"]
    assert np.all(np.isfinite(observation)) and np.isfinite(reward)
    np.testing.assert_array_equal(observation, previous)
    env.close()


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Design(-0.1, 0.5), "-0.1"),
        (lambda: DesignDistribution((0.2, 0.15), (0.4, 0.6)), "empty"),
        (lambda: RobotSettings(actuated=("rear_left_hip", "tail_wag")), "tail_wag"),
        (lambda: RobotSettings(observed_links=("front_left_claw",)), "front_left_claw"),
        (lambda: PhysicsSettings(substeps=0), "substeps"),
        (lambda: PhysicsSettings(max_joint_speed=0.0), "max_joint_speed must be null or a positive"),
        (lambda: RewardWeights(w_y=1.0), "w_y"),
        (lambda: WalkerEnv(observation="pixels"), "pixels"),
        (lambda: BatchedWalkerEnv(0), "num_robots"),
    ],
)
def test_bad_settings_raise_naming_the_value(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_bad_actions_raise():
    env = WalkerEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(3,\)"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([0.0, np.nan, 0.0, 0.0]))
    env.close()


def test_partial_reset_rebuilds_only_masked_robots():
    env = BatchedWalkerEnv(3, design=DesignDistribution.fixed(0.175, 0.5))
    env.set_seed(0)
    td = env.reset()
    for _ in range(5):
        td = env.step(td.set("action", torch.full((3, 4), 0.8)))["next"].clone()
    mask = torch.tensor([[False], [True], [False]])
    # TorchRL's contract: the reset input is the current carrier, plus the _reset mask.
    before = td.clone()
    designs = before["design"].clone()
    designs[1] = torch.tensor([0.19, 0.45])
    after = env.reset(td.update({"_reset": mask, "design": designs}))
    torch.testing.assert_close(after["observation"][[0, 2]], before["observation"][[0, 2]])
    torch.testing.assert_close(after["observation"][[0, 2]], torch.as_tensor(env._raw[[0, 2]], dtype=torch.float32))
    assert after["observation"][1, 0].abs() < 1e-3  # back at the origin
    torch.testing.assert_close(after["design"][1], torch.tensor([0.19, 0.45]))
    torch.testing.assert_close(after["design"][0], torch.tensor([0.175, 0.5]))
    assert env._steps.tolist() == [5, 0, 5]
    env.close()


def _sleeping_parallel(num_robots: int = 2) -> SleepingParallelEnv:
    return SleepingParallelEnv(2, functools.partial(BatchedWalkerEnv, num_robots), mp_start_method="fork")


def test_sleeping_parallel_env_steps_like_torchrl_parallel_env():
    actions = torch.linspace(-1, 1, 2 * 2 * 4 * 6).reshape(6, 2, 2, 4)
    trajectories = []
    for env in (ParallelEnv(2, functools.partial(BatchedWalkerEnv, 2), mp_start_method="fork"), _sleeping_parallel()):
        check_env_specs(env, seed=0)
        env.set_seed(3)
        td = env.reset()
        observations = []
        for action in actions:
            td = env.step(td.set("action", action))
            observations.append(td["next", "observation"])
            td = env.step_mdp(td)
        env.close()
        trajectories.append(torch.stack(observations))
    assert trajectories[0].shape == (6, 2, 2, 18)
    torch.testing.assert_close(trajectories[0], trajectories[1], rtol=0, atol=0)


def test_sleeping_parallel_env_parent_does_not_spin():
    # TorchRL's ParallelEnv parent spin-waits (about 80% of a core here); ours sleeps.
    env = _sleeping_parallel(num_robots=4)
    env.set_seed(0)
    env.rollout(2, break_when_any_done=False)
    cpu, wall = time.process_time(), time.perf_counter()
    env.rollout(30, break_when_any_done=False)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    env.close()
    assert cpu / wall < 0.5, f"parent used {cpu / wall:.0%} of a core while its workers stepped"


def test_sleeping_parallel_env_reports_a_worker_that_dies_mid_rollout():
    env = _sleeping_parallel(num_robots=16)
    env.set_seed(0)
    env.reset()
    threading.Timer(0.3, env._workers[1].kill).start()  # a worker spends most of its time stepping
    started = time.perf_counter()
    with pytest.raises(RuntimeError, match="worker"):
        env.rollout(1000, break_when_any_done=False)
    assert time.perf_counter() - started < 5.0  # found within seconds, not after the rollout


def test_waking_done_flags_count_only_a_set_byte_as_done():
    flags = WakingDoneFlags(multiprocessing.RawArray("b", 2), multiprocessing.get_context("fork"))
    flags.semaphores[0].release()  # a stale post, as a close command leaves behind
    started = time.perf_counter()
    assert not flags.wait(0, timeout=0.05)
    assert time.perf_counter() - started >= 0.05
    threading.Timer(0.05, flags.__setitem__, (1, 1)).start()
    assert flags.wait(1, timeout=5.0)
    assert flags[1] == 1 and flags[0] == 0


def test_sine_gait_walks_the_de_robot_forward():
    env = WalkerEnv(DesignDistribution.fixed(0.175, 0.5))
    result = walk(env, SineGait())
    env.close()
    assert result["steps"] == 100
    assert result["forward_displacement"] >= 0.3
    assert not result["physics_fault"]


def test_batched_env_partial_step_advances_only_the_masked_robots():
    env = BatchedWalkerEnv(2, design=DesignDistribution.fixed(0.175, 0.5))
    env.set_seed(0)
    td = env.reset()
    td.set("action", torch.ones(2, 4)).set("_step", torch.tensor([True, False]))
    out = env.step(td)["next"]
    env.close()
    assert not torch.equal(out["observation"][0], td["observation"][0])
    assert torch.equal(out["observation"][1], td["observation"][1])
    assert out["reward"][1].item() == 0.0 and out["reward"][0].item() != 0.0
    assert env._steps.tolist() == [1, 0]


def test_batched_env_truncates_a_faulted_robot_only():
    env = BatchedWalkerEnv(2, design=DesignDistribution.fixed(0.175, 0.5))
    env.set_seed(0)
    td = env.reset()
    # One healthy step first: the fault must repeat this step's observation, not the reset's.
    td = env.step(td.set("action", torch.full((2, 4), 0.5)))["next"]
    previous = td["observation"].clone()
    faulty = env.simulations[1]
    pybullet.resetBasePositionAndOrientation(faulty.body.body_id, (1e4, 0, 1), (0, 0, 0, 1),
                                             physicsClientId=faulty.client)
    out = env.step(td.set("action", torch.zeros(2, 4)))["next"]
    assert out["physics_fault"].flatten().tolist() == [False, True]
    assert out["truncated"].flatten().tolist() == [False, True]
    torch.testing.assert_close(out["observation"][1], previous[1])
    assert torch.isfinite(out["reward"]).all()
    # The flags handed out are the step's own: resetting the robot does not rewrite them.
    env.reset(TensorDict({"_reset": torch.tensor([[False], [True]])}, batch_size=[2]))
    assert out["physics_fault"].flatten().tolist() == [False, True]
    env.close()
