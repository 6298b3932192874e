"""Design-grid evaluation: right designs, right numbers, files that round-trip, a CLI that fails clearly."""

from __future__ import annotations

import math
import sys
import types
from dataclasses import replace

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from unipolicy_rl.envs import BatchedWalkerEnv, Design, DesignDistribution, RobotSettings, WalkerEnv
from unipolicy_rl.evaluation import (
    CSV_COLUMNS,
    DesignResult,
    episode_outcomes,
    evaluate_on_designs,
    plot_heatmaps,
    plot_training_curve,
    read_csv,
    rollout_designs,
    summarise,
    write_csv,
)

torch.set_num_threads(1)

EPISODE_LENGTH = 15  # short episodes keep the file fast; the logic does not depend on 100
ENV_KWARGS = {"episode_length": EPISODE_LENGTH}
NUM_ACTIONS = len(RobotSettings().actuated)
CONSTANT_ACTION = 0.4


class ConstantAction(torch.nn.Module):
    """The same joint targets at every step: deterministic, and enough to move the base a little."""

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.full((*observation.shape[:-1], NUM_ACTIONS), CONSTANT_ACTION)


def constant_policy() -> TensorDictModule:
    return TensorDictModule(ConstantAction(), in_keys=["observation"], out_keys=["action"])


GRID = DesignDistribution().grid(2)


@pytest.fixture(scope="module")
def results() -> list[DesignResult]:
    # 4 designs x 2 episodes on 3 robots: 3 batches, the last one padded, so batching is exercised.
    return evaluate_on_designs(constant_policy(), ENV_KWARGS, GRID, episodes_per_design=2, num_robots=3, seed=0)


def test_one_row_per_design_in_grid_order(results):
    assert [(r.length, r.density) for r in results] == [(d.length, d.density) for d in GRID]
    assert [r.design for r in results] == GRID
    assert all(r.episodes == 2 for r in results)
    assert all(r.physics_faults == 0 for r in results)


def test_deterministic_repeats_agree_and_designs_differ(results):
    # Deterministic policy + deterministic physics: repeats coincide, whichever robot ran them.
    assert all(r.std_forward_displacement == pytest.approx(0.0, abs=1e-6) for r in results)
    assert len({round(r.mean_forward_displacement, 6) for r in results}) > 1


def test_explicit_designs_reach_the_env():
    designs = [Design(0.15, 0.6), Design(0.2, 0.4)]
    env = BatchedWalkerEnv(num_robots=2, **ENV_KWARGS)
    try:
        rollout = rollout_designs(env, constant_policy(), designs)
        assert [simulation.design for simulation in env.simulations] == designs
    finally:
        env.close()
    requested = torch.tensor([[0.15, 0.6], [0.2, 0.4]])
    assert rollout.shape == (2, EPISODE_LENGTH)
    assert torch.allclose(rollout["design"], requested.unsqueeze(1).expand(2, EPISODE_LENGTH, 2))
    assert torch.allclose(rollout["next", "design"][:, -1], requested)


def test_displacement_is_the_final_base_x_and_matches_the_gym_env(results):
    env = BatchedWalkerEnv(num_robots=1, **ENV_KWARGS)
    try:
        rollout = rollout_designs(env, constant_policy(), [GRID[0]])
    finally:
        env.close()
    outcome = episode_outcomes(rollout, env.control_period)
    final_x = rollout["next", "observation"][0, -1, 0].item()
    assert outcome["forward_displacement"][0].item() == pytest.approx(final_x)
    assert results[0].mean_forward_displacement == pytest.approx(final_x, abs=1e-6)
    assert results[0].mean_forward_speed == pytest.approx(final_x / (EPISODE_LENGTH * env.control_period))

    # The gymnasium env computes the same quantities its own way: an independent check.
    gym_env = WalkerEnv(episode_length=EPISODE_LENGTH)
    gym_env.reset(options={"design": GRID[0]})
    total, truncated, info = 0.0, False, {}
    while not truncated:
        _, reward, _, truncated, info = gym_env.step(np.full(NUM_ACTIONS, CONSTANT_ACTION))
        total += reward
    gym_env.close()
    assert results[0].mean_forward_displacement == pytest.approx(info["forward_displacement"], abs=1e-5)
    assert results[0].mean_forward_speed == pytest.approx(info["mean_forward_speed"], abs=1e-4)
    assert results[0].mean_episode_reward == pytest.approx(total, rel=1e-4, abs=1e-4)


def test_an_episode_that_ends_early_is_read_up_to_its_own_end():
    # Robot 0 faults at step 1 (its later entries are padding); robot 1 runs all 3 steps.
    observation = torch.zeros(2, 3, 18)
    observation[0, :, 0] = torch.tensor([0.1, 0.2, 9.0])
    observation[1, :, 0] = torch.tensor([0.1, 0.3, 0.6])
    done = torch.tensor([[False, True, True], [False, False, True]]).unsqueeze(-1)
    fault = torch.tensor([[False, True, False], [False, False, False]]).unsqueeze(-1)
    reward = torch.ones(2, 3, 1)
    rollout = TensorDict(
        {"next": {"observation": observation, "done": done, "physics_fault": fault, "reward": reward}}, [2, 3]
    )
    outcome = episode_outcomes(rollout, control_period=0.5)
    assert outcome["steps"].tolist() == [2, 3]
    assert outcome["episode_reward"].tolist() == [2.0, 3.0]
    assert outcome["forward_displacement"].tolist() == pytest.approx([0.2, 0.6])
    assert outcome["forward_speed"].tolist() == pytest.approx([0.2 / 1.0, 0.6 / 1.5])
    assert outcome["physics_fault"].tolist() == [True, False]


def test_csv_round_trips(results, tmp_path):
    path = write_csv(results, tmp_path / "designs.csv")
    assert path.read_text().splitlines()[0].split(",") == list(CSV_COLUMNS)
    assert read_csv(path) == results


def test_summary_counts_walking_designs(results):
    walking = [replace(results[0], mean_forward_displacement=1.5), replace(results[1], mean_forward_displacement=1.0)]
    summary = summarise(walking + results[2:])
    assert summary["designs"] == 4 and summary["episodes"] == 8
    assert summary["walking_designs"] == 2 and summary["walking_fraction"] == 0.5
    assert summary["max_forward_displacement"] == 1.5
    assert summary["best_design"] == (results[0].length, results[0].density)
    assert summary["min_forward_displacement"] == min(r.mean_forward_displacement for r in results[2:])
    assert math.isclose(summary["mean_episode_reward"], sum(r.mean_episode_reward for r in results) / 4)


def test_heatmaps_and_training_curve_are_written(results, tmp_path):
    paths = plot_heatmaps(results, tmp_path, title="constant action")
    assert [path.name for path in paths] == ["heatmap_reward.png", "heatmap_displacement.png"]
    for path in paths:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 1000

    metrics = tmp_path / "metrics.csv"
    metrics.write_text("epoch,train/episode_reward,train/forward_displacement\n0,1.0,\n1,2.5,0.3\n2,4.0,0.7\n")
    curve = plot_training_curve(metrics, tmp_path / "curve.png")
    assert curve.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = [{"epoch": 0, "train/episode_reward": 1.0}, {"epoch": 1, "train/episode_reward": 2.0}]
    assert plot_training_curve(rows, tmp_path / "rows.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="train/episode_reward"):
        plot_training_curve([{"epoch": 0, "loss": 1.0}], tmp_path / "bad.png")


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="episodes_per_design"):
        evaluate_on_designs(constant_policy(), ENV_KWARGS, GRID, episodes_per_design=0)
    with pytest.raises(ValueError, match="num_robots"):
        evaluate_on_designs(constant_policy(), {"num_robots": 2}, GRID)


# -- CLI ---------------------------------------------------------------------------------
@pytest.fixture
def fake_checkpoint(tmp_path, monkeypatch):
    """A checkpoint file plus a stand-in ``unipolicy_rl.checkpoint`` that loads the constant policy."""
    path = tmp_path / "run" / "checkpoint.pt"
    path.parent.mkdir()
    path.write_bytes(b"not read by the stand-in loader")
    loaded = types.SimpleNamespace(policy=constant_policy(), env_kwargs=dict(ENV_KWARGS), config={},
                                   env_class=BatchedWalkerEnv)
    module = types.ModuleType("unipolicy_rl.checkpoint")
    module.load_policy = lambda checkpoint, device="cpu": loaded
    monkeypatch.setitem(sys.modules, "unipolicy_rl.checkpoint", module)
    return path


def test_cli_writes_csv_and_heatmaps_next_to_the_checkpoint(fake_checkpoint, capsys):
    from unipolicy_rl.evaluate import main

    summary = main([str(fake_checkpoint), "--grid", "2", "--episodes", "1"])
    out_dir = fake_checkpoint.parent / "evaluation"
    assert summary["csv"] == out_dir / "designs.csv"
    assert len(read_csv(out_dir / "designs.csv")) == 4
    assert all((out_dir / name).stat().st_size > 0 for name in ("heatmap_reward.png", "heatmap_displacement.png"))
    printed = capsys.readouterr().out
    assert "forward displacement (m)" in printed and "0.150" in printed


def test_cli_errors_name_the_problem(tmp_path, fake_checkpoint, capsys):
    from unipolicy_rl.evaluate import cli, main

    missing = tmp_path / "nowhere" / "checkpoint.pt"
    with pytest.raises(FileNotFoundError, match="nowhere"):
        main([str(missing)])
    with pytest.raises(ValueError, match="got 0"):
        main([str(fake_checkpoint), "--grid", "0"])
    with pytest.raises(ValueError, match="length range is empty"):
        main([str(fake_checkpoint), "--length-range", "0.2", "0.1"])
    with pytest.raises(SystemExit):
        cli([str(missing)])
    assert str(missing) in capsys.readouterr().err
