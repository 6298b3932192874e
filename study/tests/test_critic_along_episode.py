"""study/gym/critic_along_episode.py: a TRPO run's critic beside the discounted return that followed
along one deterministic episode of its gymnasium task."""

import subprocess
import sys
from pathlib import Path

import pytest

from study.gym.critic_along_episode import values_and_returns

ROOT = Path(__file__).resolve().parents[2]


def test_the_return_to_go_is_the_discounted_sum_of_the_episode_s_rewards(tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), "env=gym", "env.id=Pendulum-v1", "epochs=1",
                             "env.frames_per_epoch=400", "env.evaluation_episodes=1", "progress_bar=false",
                             f"hydra.run.dir={tmp_path}"], cwd=ROOT, capture_output=True, text=True, timeout=600,
                            check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    values, returns, rewards, terminated = values_and_returns(str(tmp_path / "checkpoint.pt"), seed=0)
    assert len(values) == len(returns) == len(rewards) == 200 and not terminated  # Pendulum's time limit
    assert returns[-1] == pytest.approx(rewards[-1])
    assert returns[0] == pytest.approx(sum(0.99 ** t * reward for t, reward in enumerate(rewards)), rel=1e-5)
    assert all(value == value for value in values)  # finite critic values, one per step


def test_a_walker_run_is_refused_by_name(tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), "epochs=1", "episodes_per_epoch=2",
                             "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false",
                             f"hydra.run.dir={tmp_path}"],
                            cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    with pytest.raises(ValueError, match="not an on-policy learner's run on env=gym"):
        values_and_returns(str(tmp_path / "checkpoint.pt"), seed=0)
