"""The one-off TRPO step-settings script on a run of the real train.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from study.scripts import trpo_step_settings

ROOT = Path(__file__).resolve().parents[2]
TINY = ["episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false",
        "algo.critic_epochs=2"]


def run_train(*overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, check=False)


def test_the_trpo_step_settings_benchmark_steps_a_run_s_own_batch_under_each_setting(tmp_path, capsys):
    """study/scripts/trpo_step_settings.py: from a checkpoint, one step per CG setting from the same
    weights; the first setting is the reference of the ratios."""
    run = run_train(*TINY, "epochs=1", f"hydra.run.dir={tmp_path}")
    assert run.returncode == 0, run.stderr
    benchmark = trpo_step_settings
    assert benchmark.main([str(tmp_path / "checkpoint.pt"), "--settings", "10:0.1", "2:0.1", "--batches", "1"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "cg_iters" in line]
    assert len(lines) == 2 and "(1.00x)" in lines[0] and "cg_iters   2 damping 0.1" in lines[1]
    with pytest.raises(SystemExit):
        benchmark.main([str(tmp_path / "checkpoint.pt"), "--settings", "ten:0.1"])
    with pytest.raises(SystemExit):
        benchmark.main([str(tmp_path / "checkpoint.pt"), "--batches", "0"])
