"""The tutorials' examples (docs/tutorials/) run in their quick mode, as a reader would start them."""

import math
import runpy
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run_quick(monkeypatch, name: str) -> None:
    monkeypatch.setattr(sys, "argv", [name, "--quick"])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")


def test_the_env_alone_example_runs(monkeypatch, capsys):
    _run_quick(monkeypatch, "env_alone.py")
    out = capsys.readouterr().out
    assert "observation (18,)" in out
    assert "batch (4, 10)" in out
    displacement = float(out.split("forward displacement ")[1].split(" m")[0])
    assert math.isfinite(displacement)


def test_the_trpo_pendulum_example_runs(monkeypatch, capsys):
    _run_quick(monkeypatch, "trpo_pendulum.py")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("update ")]
    assert [line.split(":")[0] for line in lines] == ["update 1", "update 2"]
    for line in lines:
        assert math.isfinite(float(line.split("episode return ")[1].split(",")[0]))
        assert 0.0 <= float(line.split("KL ")[1]) <= 0.015  # within the trust region (max_kl 0.01, line search)
