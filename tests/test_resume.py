"""A resumed run is the run it was: each learner and source, killed (SIGKILL) after a checkpoint and
resumed from that checkpoint alone (``resume=<checkpoint>``, no other setting), ends bit-identical
to the same run uninterrupted: every metrics.csv cell but the wall times, and the final policy."""

import csv
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from test_distillation import write_teacher

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.training import metrics_file as columns

ROOT = Path(__file__).resolve().parents[1]
# Tiny runs with settings away from the defaults, so a resume that fell back on a default shows.
TINY = ["episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false", "workers=1",
        "epochs=3", "checkpoint_every=1", "evaluation.every_steps=20", "seed=4"]
ON_POLICY = ["algo.critic_epochs=2", "algo.critic_minibatch_size=8", "algo.actor_hidden=[16]",
             "algo.critic_hidden=[16]"]
OFF_POLICY = ["algo.actor_hidden=[16]", "algo.critic_hidden=[16]", "algo.batch_size=8", "algo.learning_starts=10",
              "algo.buffer_capacity=1000", "algo.learning_rate=0.001"]
MOE = ["source=moe", "algo.critic_fit=inline", "imagination.steps_per_batch=60", "imagination.horizon.start=3",
       "imagination.horizon.end=5", "world_model.model.hidden=[16]", "world_model.model.members=3",
       "world_model.model.elites=2", "world_model.trainer.max_epochs=2", "imagination.stopping.max_updates=2",
       "imagination.stopping.check_every=1", "imagination.stopping.check_starts=4",
       "imagination.stopping.check_horizon=3"]
GRAMMAR = ["robot=grammar", "robot.split.train_size=2", "robot.split.held_out_size=1", "policy=token_modular",
           "evaluation.morphology_grid=1"]
CASES = {
    "trpo": [*ON_POLICY, "algo.max_kl=0.02", "algo.cg_iters=5"],
    "ppo": ["algo=ppo", *ON_POLICY, "algo.clip_epsilon=0.1", "algo.policy_epochs=2", "algo.policy_minibatch_size=8"],
    "sac": ["algo=sac", *OFF_POLICY, "algo.updates_per_step=2"],
    "crossq": ["algo=crossq", *OFF_POLICY, "algo.actor_update_every=2", "algo.batch_renorm_warmup=5"],
    "redq": ["algo=redq", *OFF_POLICY, "algo.num_critics=3", "algo.updates_per_step=2"],
    "se-moe-trpo": [*ON_POLICY, *MOE],
}


def is_time(column: str) -> bool:
    """A wall-clock column (``time/...``, ``eval/seconds``, ``model/fit_seconds``): the only ones a
    resumed run may differ in."""
    return column.startswith("time/") or column.endswith("seconds")


def train(*overrides: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(ROOT / "train.py"), *overrides], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def finished(process: subprocess.Popen, timeout: float = 400) -> str:
    out, err = process.communicate(timeout=timeout)
    assert process.returncode == 0, err
    return out


def killed_after_its_first_checkpoint(folder: Path, overrides: list[str]) -> None:
    """Starts the run in ``folder`` and SIGKILLs it as soon as its first checkpoint is written (the
    kill lands anywhere in the next epoch: before, during or after its metrics row)."""
    process = train(*overrides, f"hydra.run.dir={folder}")
    deadline = time.monotonic() + 400
    while not (folder / "checkpoint.pt").is_file():
        assert process.poll() is None, process.communicate()[1]
        assert time.monotonic() < deadline, "no checkpoint written"
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert load_checkpoint(folder / "checkpoint.pt")["epoch"] < 3, "the run ended before it was killed"


def metrics(folder: Path) -> list[dict[str, str]]:
    with (folder / columns.FILE_NAME).open(newline="") as file:
        return [{key: value for key, value in row.items() if not is_time(key)} for row in csv.DictReader(file)]


def assert_the_same_run(straight: Path, resumed: Path) -> None:
    a, b = metrics(straight), metrics(resumed)
    assert [row[columns.EPOCH] for row in b] == [row[columns.EPOCH] for row in a]  # each epoch once
    for row_a, row_b in zip(a, b, strict=True):
        assert row_a == row_b, f"epoch {row_a[columns.EPOCH]} differs after the resume"
    first, second = load_checkpoint(straight / "checkpoint.pt"), load_checkpoint(resumed / "checkpoint.pt")
    assert first["epoch"] == second["epoch"] == 3
    for key, value in first["policy"].items():
        tensors = value.items() if isinstance(value, dict) else [("", value)]
        for name, tensor in tensors:
            other = second["policy"][key][name] if name else second["policy"][key]
            assert torch.equal(tensor, other), f"policy {key} {name} differs after the resume"
    assert same_settings(first["config"]) == same_settings(second["config"])


def same_settings(config: dict) -> dict:
    """A saved config but where the run resumed from and where it logs (its folder)."""
    return {key: value for key, value in config.items() if key not in ("resume", "logger")}


def killed_and_resumed(tmp_path: Path, overrides: list[str]) -> str:
    """The run straight, and killed then resumed from its checkpoint alone into its own folder;
    returns what the resume printed."""
    straight = train(*TINY, *overrides, f"hydra.run.dir={tmp_path / 'straight'}")
    killed_after_its_first_checkpoint(tmp_path / "cut", [*TINY, *overrides])
    resumed = finished(train(f"resume={tmp_path / 'cut' / 'checkpoint.pt'}", f"hydra.run.dir={tmp_path / 'cut'}"))
    finished(straight)
    assert_the_same_run(tmp_path / "straight", tmp_path / "cut")
    return resumed


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_a_killed_run_resumed_from_its_checkpoint_alone_is_the_run_it_was(case, tmp_path):
    printed = killed_and_resumed(tmp_path, CASES[case])
    assert "resumed from" in printed
    assert not [line for line in printed.splitlines() if line.startswith("resume:")]  # no setting changed


@pytest.mark.slow
def test_a_killed_distillation_resumed_from_its_checkpoint_alone_is_the_run_it_was(tmp_path):
    teachers = [write_teacher(tmp_path / f"teacher{index}.pt", f"robot.specialist={index}", seed=index)
                for index in (0, 1)]
    killed_and_resumed(tmp_path, [*GRAMMAR, "algo=distill", f"algo.teachers=[{teachers[0]},{teachers[1]}]",
                                  "algo.updates_per_epoch=3", "algo.batch_size=8", "algo.learning_rate=0.002"])


GYM = ["env=gym", "env.id=Pendulum-v1", "env.frames_per_epoch=50", "evaluation.every_steps=50",
       "env.evaluation_episodes=1", "progress_bar=false", "epochs=3", "checkpoint_every=1", "seed=4"]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["se-moe-trpo", "sac"])
def test_a_killed_gym_run_resumed_from_its_checkpoint_alone_is_the_run_it_was(case, tmp_path):
    overrides = [*GYM, *CASES[case]]
    straight = train(*overrides, f"hydra.run.dir={tmp_path / 'straight'}")
    killed_after_its_first_checkpoint(tmp_path / "cut", overrides)
    printed = finished(train(f"resume={tmp_path / 'cut' / 'checkpoint.pt'}", f"hydra.run.dir={tmp_path / 'cut'}"))
    finished(straight)
    assert_the_same_run(tmp_path / "straight", tmp_path / "cut")
    assert not [line for line in printed.splitlines() if line.startswith("resume:")]
