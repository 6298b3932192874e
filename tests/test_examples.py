"""The scripts in examples/ run as a user would copy them (a few tiny epochs each)."""

import math
import runpy
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_the_me_trpo_example_runs_its_loop(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["me_trpo.py", "--epochs", "2", "--robots", "2", "--episode-length", "10"])
    runpy.run_path(str(EXAMPLES / "me_trpo.py"), run_name="__main__")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("epoch ")]
    assert [line.split(":")[0] for line in lines] == ["epoch 1", "epoch 2"]
    assert all(math.isfinite(float(line.split("real return ")[1].split(",")[0])) for line in lines)
    assert all("imagined updates" in line for line in lines)


def test_the_mbpo_example_runs_its_loop(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["mbpo.py", "--epochs", "2", "--robots", "2", "--episode-length", "10"])
    runpy.run_path(str(EXAMPLES / "mbpo.py"), run_name="__main__")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("epoch ")]
    assert [line.split(":")[0] for line in lines] == ["epoch 1", "epoch 2"]
    assert all(math.isfinite(float(line.split("critic loss ")[1])) for line in lines)
    # one batch of imagination.steps_per_batch (2,000) model transitions per fit, whatever the horizon
    assert [int(line.split(" model transitions")[0].split(", ")[-1]) for line in lines] == [2000, 4000]
