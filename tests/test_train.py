"""train.py: configs compose, a run checkpoints, resumes bit-identically, and its policy loads."""

import csv
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from unipolicy_rl.checkpoint import load_checkpoint, load_policy, save_checkpoint
from unipolicy_rl.envs import WalkerEnv

ROOT = Path(__file__).resolve().parents[1]
TINY = ["episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false",
        "algo.critic_epochs=2"]


def run_train(*overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, check=False)


@pytest.mark.parametrize(("source", "length_range"), [("de", [0.175, 0.175]), ("se", [0.15, 0.2])])
def test_config_composes_for_every_source(source, length_range):
    result = run_train(f"source={source}", "--cfg", "job")
    assert result.returncode == 0, result.stderr
    cfg = OmegaConf.create(result.stdout)
    assert cfg.source.name == source
    assert list(cfg.design.length_range) == length_range
    assert cfg.epochs == 600 and cfg.episodes_per_epoch == 10 and cfg.algo.max_kl == 0.01


def test_unknown_override_is_a_clear_error():
    result = run_train("source=nope", "--cfg", "job")
    assert result.returncode != 0
    assert "nope" in result.stderr


def test_resume_continues_exactly_as_an_uninterrupted_run(tmp_path):
    straight = run_train(*TINY, "epochs=4", f"hydra.run.dir={tmp_path / 'straight'}")
    assert straight.returncode == 0, straight.stderr
    first = run_train(*TINY, "epochs=2", f"hydra.run.dir={tmp_path / 'first'}")
    assert first.returncode == 0, first.stderr
    resumed = run_train(*TINY, "epochs=4", f"resume={tmp_path / 'first' / 'checkpoint.pt'}",
                        f"hydra.run.dir={tmp_path / 'resumed'}")
    assert resumed.returncode == 0, resumed.stderr
    a = load_checkpoint(tmp_path / "straight" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "resumed" / "checkpoint.pt")
    assert a["epoch"] == b["epoch"] == 4
    for name in ("actor", "critic"):
        for key, value in a[name].items():
            assert torch.equal(value, b[name][key]), f"{name}.{key} differs after resume"
    torch.testing.assert_close(a["observation_loc"], b["observation_loc"], rtol=0, atol=0)
    # The run ends with a saved policy that acts on a plain WalkerEnv observation.
    loaded = load_policy(tmp_path / "straight" / "checkpoint.pt")
    env = WalkerEnv()
    observation, _ = env.reset(seed=0)
    action = loaded.act(observation)
    env.close()
    assert action.shape == (4,) and np.all(np.isfinite(action))
    assert (tmp_path / "straight" / "evaluation" / "designs.csv").is_file()
    assert (tmp_path / "straight" / "metrics.csv").read_text().count("\n") == 5  # header + 4 epochs


def test_a_de_run_is_evaluated_over_the_se_grid(tmp_path):
    result = run_train(*TINY, "source=de", "workers=1", "epochs=1", "evaluation.grid=2", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    with (tmp_path / "evaluation" / "designs.csv").open() as file:
        designs = {(float(row["length"]), float(row["density"])) for row in csv.DictReader(file)}
    assert designs == {(0.15, 0.4), (0.15, 0.6), (0.2, 0.4), (0.2, 0.6)}  # not just DE's (0.175, 0.5)


def test_sigterm_saves_the_finished_epochs_and_exits_cleanly(tmp_path):
    run_dir = tmp_path / "killed"
    process = subprocess.Popen([sys.executable, str(ROOT / "train.py"), *TINY, "epochs=100000",
                                f"hydra.run.dir={run_dir}"], cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    metrics = run_dir / "metrics.csv"
    deadline = time.monotonic() + 120
    while not (metrics.is_file() and metrics.read_text().count("\n") >= 3) and time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()[1]
        time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 0, stderr
    assert "stopped: saved epoch" in stdout
    # The checkpoint holds every epoch that finished, not just the last periodic one.
    finished = metrics.read_text().count("\n") - 1
    assert load_checkpoint(run_dir / "checkpoint.pt")["epoch"] == finished >= 2


def test_checkpoints_are_written_atomically(tmp_path, monkeypatch):
    path = save_checkpoint(tmp_path / "checkpoint.pt", {"epoch": 1})

    def exploding_save(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", exploding_save)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, {"epoch": 2})
    assert load_checkpoint(path)["epoch"] == 1  # the old checkpoint survived intact
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no temporary left behind


def test_missing_checkpoint_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.pt"):
        load_checkpoint(tmp_path / "nowhere.pt")
