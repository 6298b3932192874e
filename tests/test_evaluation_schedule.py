"""The periodic evaluation's schedule in real env steps, and over a resume."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from unipolicy_rl.evaluation import DesignResult
from unipolicy_rl.settings import evaluation_plan
from unipolicy_rl.training import metrics_file as columns
from unipolicy_rl.training import progress
from unipolicy_rl.training.progress import PeriodicEvaluation, evaluation_points, evaluations_done

ROOT = Path(__file__).resolve().parents[1]


# -- the schedule ------------------------------------------------------------------------
def schedule_config(episodes_per_epoch: int = 10, **evaluation):
    """The composed config, epochs of ``episodes_per_epoch`` x 100 steps (1,000 by default), a 2 x 2
    grid, and ``evaluation`` overrides."""
    overrides = [f"episodes_per_epoch={episodes_per_epoch}", "robot.episode_length=100", "evaluation.grid=2",
                 *(f"evaluation.{key}={value}" for key, value in evaluation.items())]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=overrides)


EVALUATION_SECONDS = 0.01  # how long the stubbed grid evaluation takes


@pytest.fixture
def grid_stub(monkeypatch):
    """The grid evaluation replaced by fixed figures (the n-th call walks n / 2 m on every design)."""
    calls = []

    def evaluate(policy, env_kwargs, designs, episodes_per_design, seed):
        time.sleep(EVALUATION_SECONDS)
        calls.append(len(designs))
        metres = len(calls) / 2
        return [DesignResult(d.length, d.density, 1, 10 * metres, 0.0, metres, 0.0, metres / 10, 0) for d in designs]

    monkeypatch.setattr(progress, "evaluate_on_designs", evaluate)
    return calls


def evaluated_epochs(evaluation: PeriodicEvaluation, epochs) -> dict[int, dict]:
    """Epoch -> the evaluation's metrics, for the epochs it evaluated after (as train.py calls it)."""
    epoch_steps = evaluation.plan.epoch_steps
    return {epoch: metrics for epoch in epochs if (metrics := evaluation(epoch, epoch * epoch_steps, policy=None))}


SCHEDULE = {"every_steps": 2000, "dense_until": 10000, "then_every_steps": 5000}


def test_the_evaluation_runs_at_the_schedule_points_in_real_steps(grid_stub):
    cfg = schedule_config(**SCHEDULE)
    evaluation = PeriodicEvaluation(evaluation_plan(cfg))
    done = evaluated_epochs(evaluation, range(1, 21))
    assert list(done) == [2, 4, 6, 8, 10, 15, 20]
    assert len(grid_stub) == 7 and grid_stub[0] == 4  # one episode per design of the 2 x 2 grid
    # The evaluations' own episodes and steps, cumulative, apart from the training steps.
    assert [m[columns.EVAL_EPISODES] for m in done.values()] == [4.0, 8.0, 12.0, 16.0, 20.0, 24.0, 28.0]
    assert done[20][columns.EVAL_ENV_STEPS] == 28 * 100
    # and each evaluation's own wall time (not cumulative: the league sums it)
    assert all(EVALUATION_SECONDS <= m[columns.EVAL_SECONDS] < 1.0 for m in done.values())
    assert done[4][columns.GRID_MEAN] == 1.0 and evaluation.best["epoch"] == 20  # each walks further: the last


def test_a_resumed_evaluation_continues_at_the_same_points(grid_stub):
    cfg = schedule_config(**SCHEDULE)
    straight = evaluated_epochs(PeriodicEvaluation(evaluation_plan(cfg)), range(1, 21))
    first = PeriodicEvaluation(evaluation_plan(cfg))
    evaluated_epochs(first, range(1, 8))
    # (a fresh process)
    resumed = evaluated_epochs(PeriodicEvaluation(evaluation_plan(cfg), best=first.best), range(8, 21))
    assert list(resumed) == [8, 10, 15, 20]
    assert [m[columns.EVAL_EPISODES] for m in resumed.values()] == \
        [straight[epoch][columns.EVAL_EPISODES] for epoch in resumed]


def test_an_epoch_crossing_several_points_evaluates_once_and_zero_turns_it_off(grid_stub):
    cfg = schedule_config(episodes_per_epoch=35, **SCHEDULE)
    # 3,500-step epochs: the first crosses 2,000, the second 4,000 and 6,000 (one evaluation), the
    # third 8,000 and 10,000, the fourth (to 14,000) none, then 15,000 and 20,000.
    done = evaluated_epochs(PeriodicEvaluation(evaluation_plan(cfg)), range(1, 7))
    assert list(done) == [1, 2, 3, 5, 6] and done[6][columns.EVAL_EPISODES] == 5 * 4
    off = schedule_config(every_steps=0)
    assert not evaluated_epochs(PeriodicEvaluation(evaluation_plan(off)), range(1, 30))


@pytest.mark.parametrize(("every", "until", "then", "epoch"),
                         list(itertools.product((1, 3, 7), (0, 10, 21), (1, 4, 9), (1, 2, 5, 8))))
def test_the_evaluation_count_is_the_number_of_epochs_that_crossed_a_point(every, until, then, epoch):
    crossed = 0
    for steps in range(epoch, 200, epoch):
        crossed += evaluation_points(steps, every, until, then) > evaluation_points(steps - epoch, every, until, then)
        assert evaluations_done(steps, epoch, every, until, then) == crossed


def test_the_schedule_is_every_step_setting_up_to_the_dense_part_then_the_sparse_one():
    points = [s for s in range(1, 130_001) if evaluation_points(s, 2000, 100_000, 10_000)
              > evaluation_points(s - 1, 2000, 100_000, 10_000)]
    assert points[:3] == [2000, 4000, 6000] and points[49:] == [100_000, 110_000, 120_000, 130_000]


