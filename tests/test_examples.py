"""The scripts in examples/ run as a user would copy them, in their quick mode (``--quick``: 2 tiny epochs)."""

import math
import runpy
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.mark.parametrize("script", sorted(path.name for path in EXAMPLES.glob("*.py")))
def test_every_example_has_a_quick_mode_that_its_test_runs(script):
    source = (EXAMPLES / script).read_text()
    assert '"--quick"' in source, f"examples/{script}: add a --quick mode (and a test here that runs it)"
    assert f'"{script}", "--quick"' in Path(__file__).read_text(), f"examples/{script}: run its --quick mode here"


def test_the_me_trpo_example_runs_its_loop(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["me_trpo.py", "--quick"])
    runpy.run_path(str(EXAMPLES / "me_trpo.py"), run_name="__main__")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("epoch ")]
    assert [line.split(":")[0] for line in lines] == ["epoch 1", "epoch 2"]
    assert all(math.isfinite(float(line.split("real return ")[1].split(",")[0])) for line in lines)
    assert all("imagined updates" in line for line in lines)


def test_the_mbpo_example_runs_its_loop(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["mbpo.py", "--quick"])
    runpy.run_path(str(EXAMPLES / "mbpo.py"), run_name="__main__")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("epoch ")]
    assert [line.split(":")[0] for line in lines] == ["epoch 1", "epoch 2"]
    assert all(math.isfinite(float(line.split("critic loss ")[1])) for line in lines)
    # one batch of imagination.steps_per_batch (2,000) model transitions per fit, whatever the horizon
    assert [int(line.split(" model transitions")[0].split(", ")[-1]) for line in lines] == [2000, 4000]


def test_the_own_env_example_runs_me_trpo_on_pendulum_with_a_known_and_a_learned_reward(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["own_env_pendulum.py", "--quick"])
    runpy.run_path(str(EXAMPLES / "own_env_pendulum.py"), run_name="__main__")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("epoch ")]
    assert [line.split(",")[0] for line in lines] == ["epoch 1: known reward", "epoch 2: known reward",
                                                      "epoch 1: learned reward", "epoch 2: learned reward"]
    assert [int(line.split("real steps ")[1].split(",")[0]) for line in lines] == [200, 400, 200, 400]
    # Pendulum's return lies in [-16.3 * 200, 0] per episode.
    assert all(-3300 < float(line.split("return ")[1].split(",")[0]) <= 0 for line in lines)


def test_the_env_alone_example_runs(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["env_alone.py", "--quick"])
    runpy.run_path(str(EXAMPLES / "env_alone.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "observation (18,)" in out
    assert "batch (4, 10)" in out
    displacement = float(out.split("forward displacement ")[1].split(" m")[0])
    assert math.isfinite(displacement)


def test_the_trpo_pendulum_example_runs(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["trpo_pendulum.py", "--quick"])
    runpy.run_path(str(EXAMPLES / "trpo_pendulum.py"), run_name="__main__")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("update ")]
    assert [line.split(":")[0] for line in lines] == ["update 1", "update 2"]
    for line in lines:
        assert math.isfinite(float(line.split("episode return ")[1].split(",")[0]))
        assert 0.0 <= float(line.split("KL ")[1]) <= 0.015  # within the trust region (max_kl 0.01, line search)
