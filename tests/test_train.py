"""train.py: configs compose, a run checkpoints, resumes bit-identically, and its policy loads."""

import csv
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from unipolicy_rl.checkpoint import load_checkpoint, load_policy, save_checkpoint
from unipolicy_rl.envs import DesignDistribution, WalkerEnv
from unipolicy_rl.envs.design import SE_DENSITY_RANGE, SE_LENGTH_RANGE

ROOT = Path(__file__).resolve().parents[1]
TINY = ["episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false",
        "algo.critic_epochs=2"]


def run_train(*overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, check=False)


def assert_same_training_state(a: dict, b: dict, world_model: bool = False) -> None:
    """Two checkpoints hold the same actor and critic (and world model) weights, tensor for tensor:
    what a straight run and a resumed one must agree on."""
    for name in ("actor", "critic"):
        for key, value in a["learner"][name].items():
            assert torch.equal(value, b["learner"][name][key]), f"{name}.{key} differs after resume"
    for key, value in (a["world_model"] if world_model else {}).items():
        assert torch.equal(value, b["world_model"][key]), f"world model {key} differs after resume"


def run_train_with(patch: str, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """train.py with ``patch`` (Python source) run first: to make the updater fail on purpose."""
    script = "\n".join(["import runpy, sys", patch, f"sys.argv = ['train.py', *{list(overrides)!r}]",
                        f"runpy.run_path({str(ROOT / 'train.py')!r}, run_name='__main__')"])
    return subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          check=False)


# Every batch reaches the updater with one NaN reward, as a diverging simulation would send it.
POISON_REWARDS = """
from unipolicy_rl.objectives.updater import TRPOUpdater
_update = TRPOUpdater.update
def poisoned(self, batch):
    batch["next", "reward"][..., 0, :] = float("nan")
    return _update(self, batch)
TRPOUpdater.update = poisoned
"""


def test_train_py_prints_the_config_it_composed():
    # (every option of every group composes in-process in test_config_groups)
    result = run_train("source=de", "--cfg", "job")
    assert result.returncode == 0, result.stderr
    cfg = OmegaConf.create(result.stdout)
    assert cfg.source.name == "de"
    assert list(cfg.design.length_range) == [0.175, 0.175]
    assert cfg.epochs == 600 and cfg.episodes_per_epoch == 10 and cfg.algo.max_kl == 0.01


@pytest.mark.slow
def test_the_design_space_is_written_once_and_agrees_with_the_code():
    """SE's ranges, the evaluation grid's and the library's defaults are one fact."""
    result = run_train("source=se", "--cfg", "job")
    cfg = OmegaConf.create(result.stdout)
    expected = [list(SE_LENGTH_RANGE), list(SE_DENSITY_RANGE)]
    assert [list(cfg.design_space.length_range), list(cfg.design_space.density_range)] == expected
    assert [list(cfg.design.length_range), list(cfg.design.density_range)] == expected
    assert [list(cfg.evaluation.length_range), list(cfg.evaluation.density_range)] == expected
    moved = OmegaConf.create(run_train("source=se", "design_space.length_range=[0.1,0.3]", "--cfg", "job").stdout)
    assert list(moved.design.length_range) == list(moved.evaluation.length_range) == [0.1, 0.3]


def test_unknown_override_is_a_clear_error():
    result = run_train("source=nope", "--cfg", "job")
    assert result.returncode != 0
    assert "nope" in result.stderr


class StraightAndResumed(NamedTuple):
    straight: dict  # the checkpoint of the run of ``total`` epochs
    resumed: dict   # the checkpoint of the run stopped after ``first`` epochs and resumed to ``total``
    output: str     # what the straight run printed


def straight_and_resumed(tmp_path: Path, overrides: list[str], first: int, total: int) -> StraightAndResumed:
    """A run of ``total`` epochs and one stopped after ``first`` and resumed to ``total`` (folders
    ``straight``, ``first``, ``resumed`` under ``tmp_path``); each run must succeed."""
    straight = run_train(*overrides, f"epochs={total}", f"hydra.run.dir={tmp_path / 'straight'}")
    assert straight.returncode == 0, straight.stderr
    stopped = run_train(*overrides, f"epochs={first}", f"hydra.run.dir={tmp_path / 'first'}")
    assert stopped.returncode == 0, stopped.stderr
    resumed = run_train(*overrides, f"epochs={total}", f"resume={tmp_path / 'first' / 'checkpoint.pt'}",
                        f"hydra.run.dir={tmp_path / 'resumed'}")
    assert resumed.returncode == 0, resumed.stderr
    return StraightAndResumed(load_checkpoint(tmp_path / "straight" / "checkpoint.pt"),
                              load_checkpoint(tmp_path / "resumed" / "checkpoint.pt"), straight.stdout)


@pytest.mark.slow
def test_resume_continues_exactly_as_an_uninterrupted_run(tmp_path):
    a, b, _ = straight_and_resumed(tmp_path, TINY, first=2, total=4)
    assert a["epoch"] == b["epoch"] == 4
    assert_same_training_state(a, b)
    torch.testing.assert_close(a["policy"]["observation_loc"], b["policy"]["observation_loc"], rtol=0, atol=0)
    # The run ends with a saved policy that acts on a plain WalkerEnv observation.
    loaded = load_policy(tmp_path / "straight" / "checkpoint.pt")
    env = WalkerEnv()
    observation, _ = env.reset(seed=0)
    action = loaded.act(observation)
    env.close()
    assert action.shape == (4,) and np.all(np.isfinite(action))
    assert (tmp_path / "straight" / "evaluation" / "designs.csv").is_file()
    assert (tmp_path / "straight" / "metrics.csv").read_text().count("\n") == 5  # header + 4 epochs


# robot=grammar on a split of 3 training and 2 held-out morphologies, a small transformer.
GRAMMAR_TINY = [*TINY, "robot=grammar", "policy=token_transformer", "robot.split.train_size=3",
                "robot.split.held_out_size=2", "policy.network.d_model=16", "policy.network.feedforward=32",
                "evaluation.every_steps=1", "evaluation.morphology_grid=1", "algo.fisher_fraction=0.5"]


@pytest.mark.slow
def test_a_grammar_run_trains_evaluates_per_morphology_and_resumes_exactly(tmp_path):
    from unipolicy_rl.envs import MorphologyWalkerEnv
    from unipolicy_rl.envs.tokens import TOKENS

    # Advantages standardised per morphology (algo.advantage_groups): the batch carries each robot's.
    grouped = [*GRAMMAR_TINY, "algo.advantage_groups=morphology"]
    a, b, output = straight_and_resumed(tmp_path, [*grouped, "evaluation.morphologies=all"], first=1, total=2)
    assert a["epoch"] == b["epoch"] == 2
    assert (a["observation_dim"], a["action_dim"]) == (28, 29)  # F features per token, L token slots
    assert_same_training_state(a, b)
    assert torch.equal(a["policy"]["observation_loc"], b["policy"]["observation_loc"])
    assert a["best_evaluation"] == b["best_evaluation"]
    # Periodic evaluations: the usual eval/ columns over every (morphology, design) cell, each epoch.
    with (tmp_path / "straight" / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 2 and all(row["eval/grid_mean_displacement"] for row in rows)
    assert [float(row["eval/episodes"]) for row in rows] == [5.0, 10.0]  # 3 + 2 morphologies, one design
    with (tmp_path / "straight" / "evaluation" / "periodic_morphologies.csv").open() as file:
        assert [(row["epoch"], row["morphology"]) for row in csv.DictReader(file)] == \
            [(epoch, str(index)) for epoch in ("1", "2") for index in range(5)]
    # The final evaluation: every morphology on the evaluation.grid designs, and its summary.
    with (tmp_path / "straight" / "evaluation" / "morphologies.csv").open() as file:
        assert [row["morphology"] for row in csv.DictReader(file)] == ["0", "1", "2", "3", "4"]
    assert "morphologies 5: walking" in output
    # The saved policy rebuilds from its checkpoint and drives the env it trained on.
    loaded = load_policy(tmp_path / "straight" / "checkpoint.pt")
    assert loaded.env_class is MorphologyWalkerEnv
    env = loaded.env_class(2, **loaded.env_kwargs)
    with torch.no_grad():
        step = loaded.policy(env.reset())
    env.close()
    assert step["action"].shape == (2, 29) and torch.isfinite(step["action"]).all() and TOKENS in step.keys()
    assert (step["action"][~step["action_mask"]] == 0).all()
    with pytest.raises(ValueError, match="link tokens"):
        loaded.act(np.zeros(18))

    # python -m unipolicy_rl.evaluate takes it too, on any side of the split.
    from unipolicy_rl.evaluate import main as evaluate

    summary = evaluate([str(tmp_path / "straight" / "checkpoint.pt"), "--grid", "1", "--morphologies", "held_out",
                        "--out", str(tmp_path / "held_out")])
    assert summary["morphologies"] == 2 and summary["designs"] == 2


@pytest.mark.slow
def test_a_modular_policy_trains_on_the_gait_clock_and_its_checkpoint_drives_a_clocked_env(tmp_path):
    from unipolicy_rl.envs.tokens import CLOCK

    clocked = [*TINY, "robot=grammar", "policy=token_modular", "robot.split.train_size=3",
               "robot.split.held_out_size=2", "robot.clock_frequency=1.5", "evaluation.every_steps=0"]
    run = run_train(*clocked, "epochs=1", f"hydra.run.dir={tmp_path}")
    assert run.returncode == 0, run.stderr
    loaded = load_policy(tmp_path / "checkpoint.pt")
    assert CLOCK in loaded.policy.in_keys and loaded.env_kwargs["clock_frequency"] == 1.5
    env = loaded.env_class(2, **loaded.env_kwargs)
    with torch.no_grad():
        first = loaded.policy(env.reset())
        moved = loaded.policy(first.clone().set(CLOCK, -first[CLOCK]))
    env.close()
    real = first["action_mask"]
    assert (first["loc"] - moved["loc"])[real].abs().max() > 0  # the trained policy reads the phase


@pytest.mark.slow
def test_a_grammar_run_collects_on_ray_actors(tmp_path):
    """collector.backend=ray with robots of several morphologies: the actors step the padded
    token env, and the run trains an epoch on what they send and checkpoints it."""
    pytest.importorskip("ray")
    run = run_train(*GRAMMAR_TINY, "collector.backend=ray", "workers=2", "epochs=1", f"hydra.run.dir={tmp_path}")
    assert run.returncode == 0, run.stderr
    with (tmp_path / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 1 and float(rows[0]["real_env_steps"]) == 20  # 2 episodes of 10 steps
    assert load_checkpoint(tmp_path / "checkpoint.pt")["epoch"] == 1


@pytest.mark.slow
def test_a_de_run_is_evaluated_over_the_se_grid(tmp_path):
    result = run_train(*TINY, "source=de", "workers=1", "epochs=1", "evaluation.grid=2", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    assert "Warning" not in result.stderr  # e.g. TorchRL's auto_register_policy_transforms FutureWarning
    with (tmp_path / "evaluation" / "designs.csv").open() as file:
        designs = {(float(row["length"]), float(row["density"])) for row in csv.DictReader(file)}
    assert designs == {(0.15, 0.4), (0.15, 0.6), (0.2, 0.4), (0.2, 0.6)}  # not just DE's (0.175, 0.5)


@pytest.mark.slow
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


@pytest.mark.slow
def test_the_best_periodic_evaluation_keeps_its_policy_apart_from_the_run(tmp_path):
    from unipolicy_rl.evaluation import evaluate_on_designs, grid_score, summarise

    result = run_train(*TINY, "workers=1", "epochs=4", "evaluation.every_steps=1", "evaluation.grid=2",
                       f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    with (tmp_path / "metrics.csv").open() as file:
        evaluations = [(int(row["epoch"]), float(row["eval/grid_mean_displacement"]),
                        float(row["eval/grid_min_displacement"])) for row in csv.DictReader(file)
                       if row.get("eval/grid_mean_displacement")]
    assert [epoch for epoch, _, _ in evaluations] == [1, 2, 3, 4]
    best_epoch, best_mean, _ = max(evaluations, key=lambda e: grid_score(e[1], e[2]))  # the first of equals
    best = load_checkpoint(tmp_path / "best.pt")
    assert best["epoch"] == best_epoch and best["best_evaluation"]["epoch"] == best_epoch
    assert "collector" not in best and load_checkpoint(tmp_path / "checkpoint.pt")["best_evaluation"] == \
        best["best_evaluation"]
    assert f"best periodic evaluation: epoch {best_epoch}" in result.stdout
    # best.pt is the policy that was evaluated: the same grid gives the same figure again.
    loaded = load_policy(tmp_path / "best.pt")
    again = summarise(evaluate_on_designs(loaded.policy, dict(loaded.env_kwargs), DesignDistribution().grid(2),
                                          episodes_per_design=1, seed=0))
    assert again["mean_forward_displacement"] == pytest.approx(best_mean, abs=1e-6)
    # It holds a policy, not a run: a resume from it is refused by name.
    refused = run_train(*TINY, "workers=1", "epochs=5", f"resume={tmp_path / 'best.pt'}",
                        f"hydra.run.dir={tmp_path / 'resumed'}")
    assert refused.returncode != 0 and "holds a policy only" in refused.stderr


def test_checkpoints_are_written_atomically(tmp_path, monkeypatch):
    path = save_checkpoint(tmp_path / "checkpoint.pt", {"epoch": 1, "actor": {}, "config": {}})

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


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"not a checkpoint at all", "is not a readable checkpoint"),
        ("torch", "is not a unipolicy_rl checkpoint"),
        ("newer", "checkpoint format 99, newer"),
    ],
)
def test_a_file_that_is_not_our_checkpoint_is_one_clear_error(tmp_path, content, match):
    path = tmp_path / "bad.pt"
    if content == "torch":
        torch.save({"weights": torch.zeros(2)}, path)
    elif content == "newer":
        torch.save({"format": 99, "actor": {}, "config": {}}, path)
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError, match=match) as error:
        load_checkpoint(path)
    assert "bad.pt" in str(error.value)


@pytest.mark.slow
def test_a_resume_takes_the_checkpoints_network_and_refuses_a_conflicting_override(tmp_path):
    first = run_train(*TINY, "epochs=1", "workers=1", "algo.actor_hidden=[16]", f"hydra.run.dir={tmp_path / 'a'}")
    assert first.returncode == 0, first.stderr
    checkpoint = tmp_path / "a" / "checkpoint.pt"
    conflicting = run_train(*TINY, "epochs=2", "workers=1", "algo.actor_hidden=[32]", f"resume={checkpoint}",
                            f"hydra.run.dir={tmp_path / 'b'}")
    assert conflicting.returncode != 0
    assert "algo.actor_hidden: [32] here, [16] in the checkpoint" in conflicting.stderr
    assert "size mismatch" not in conflicting.stderr
    resumed = run_train(*TINY, "epochs=2", "workers=1", f"resume={checkpoint}", f"hydra.run.dir={tmp_path / 'c'}")
    assert resumed.returncode == 0, resumed.stderr
    assert "actor_hidden" not in resumed.stdout  # the run's own setting, not a change
    assert load_checkpoint(tmp_path / "c" / "checkpoint.pt")["config"]["algo"]["actor_hidden"] == [16]


def composed(*overrides: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(ROOT / "conf"), version_base=None):
        return compose("config", overrides=list(overrides))


def saved_run_config(*overrides: str) -> dict:
    """The config a run with ``overrides`` saves in its checkpoint (resolved, as train.py saves it)."""
    def resolved(node):  # Hydra's runtime values (the run's name, its folder) exist inside a run only
        if isinstance(node, dict):
            return {key: resolved(value) for key, value in node.items()}
        return "from-the-run" if isinstance(node, str) and "${hydra:" in node else node

    return resolved(OmegaConf.to_container(composed(*overrides), resolve=False))


def test_a_resume_continues_with_the_runs_own_settings_and_this_command_lines(capsys):
    """A checkpoint without group choices (format 3): the run's settings, one by one."""
    from unipolicy_rl.resume import settings_for_resume

    saved = saved_run_config("source=moe", "seed=3", "imagination.fit_every=2", "algo.max_kl=0.02",
                             "logger=tensorboard")
    saved["a_setting_since_removed"] = 1
    saved["an_object_since_removed"] = {"_target_": "old.Thing", "size": 2}
    here = composed("source=moe", "epochs=200")
    resumed = settings_for_resume(here, {"config": saved}, named=["epochs"], choices={}, path="run.pt")
    # What the command line did not name is the run's, not this configuration's default ...
    assert (resumed.seed, resumed.imagination.fit_every, resumed.algo.max_kl) == (3, 2, 0.02)
    # ... an object built from another class is the run's whole, not mixed with the default's ...
    # (where it writes following this run's folder, not the saved one's).
    assert resumed.logger._target_ == saved["logger"]["_target_"] != here.logger._target_
    assert set(resumed.logger) == set(saved["logger"])
    assert OmegaConf.to_container(resumed.logger)["log_dir"] == "${hydra:runtime.output_dir}/logs"
    # ... and what it named is this run's.
    assert resumed.epochs == 200
    out = capsys.readouterr().out
    assert "resume: epochs: 100 -> 200" in out and "logger: the checkpoint's, whole (a " in out
    assert "seed" not in out and "fit_every" not in out  # the run's own settings, not changes
    assert ("a_setting_since_removed, an_object_since_removed._target_, an_object_since_removed.size are not "
            "settings of this version") in out
    assert "a_setting_since_removed" not in resumed and "an_object_since_removed" not in resumed
    # Nothing differs, nothing is said.
    settings_for_resume(composed("source=moe", "seed=3"), {"config": saved_run_config("source=moe", "seed=3")},
                        named=["seed"], choices={}, path="run.pt")
    assert capsys.readouterr().out == ""


MOE_TINY = [*TINY, "source=moe", "workers=1", "evaluation.every_steps=1", "imagination.steps_per_batch=60",
            "imagination.horizon.start=3", "imagination.horizon.end=5", "imagination.horizon.first_epoch=1",
            "imagination.horizon.last_epoch=3", "world_model.model.hidden=[16]",
            "world_model.model.members=3", "world_model.model.elites=2", "world_model.trainer.max_epochs=2",
            "imagination.stopping.max_updates=4", "imagination.stopping.check_every=2",
            "imagination.stopping.check_starts=4", "imagination.stopping.check_horizon=3"]


@pytest.mark.slow
def test_a_model_based_run_resumes_exactly_and_logs_where_its_data_came_from(tmp_path):
    a, b, _ = straight_and_resumed(tmp_path, MOE_TINY, first=1, total=3)
    assert a["epoch"] == b["epoch"] == 3
    assert_same_training_state(a, b, world_model=True)
    assert a["collector"] == b["collector"] == {"epoch": 3, "real_env_steps": 60}
    with (tmp_path / "straight" / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    real = [row for row in rows if row["imagined"] == "0.0"]
    imagined = [row for row in rows if row["imagined"] == "1.0"]
    assert [row["real_env_steps"] for row in real] == ["20.0", "40.0", "60.0"]
    assert real[0]["train/episode_reward"] and not imagined[0]["train/episode_reward"]
    assert imagined[0]["imagined/reward_per_step"] and real[0]["model/validation_mse"]
    # The model's error on each epoch's new states is measured before it fits them: from the second epoch on.
    assert not real[0]["model/fresh_error"] and all(float(row["model/fresh_error"]) > 0 for row in real[1:])
    assert all(row["eval/grid_min_displacement"] for row in real)  # evaluation.every_steps=1
    # Each real epoch logs the CPU seconds of its collection and updates (at most a few busy processes' worth).
    for row in real:
        assert 0 < float(row["time/cpu"]) < 4 * (float(row["time/collect"]) + float(row["time/update"])) + 0.5
    assert not any(row["time/cpu"] for row in imagined)
    # The run is named for what ran: the design, the world model and the algorithm.
    assert (tmp_path / "straight" / "logs" / "se-moe-trpo_seed0").is_dir()


@pytest.mark.slow
def test_a_model_fitted_every_second_epoch_still_trains_the_policy_on_imagined_data_every_epoch(tmp_path):
    result = run_train(*MOE_TINY, "epochs=3", "imagination.fit_every=2", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    with (tmp_path / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    fitted = {row["epoch"]: bool(row["model/fit_steps"]) for row in rows if row["imagined"] == "0.0"}
    assert fitted == {"1": True, "2": False, "3": True}
    assert {row["epoch"] for row in rows if row["imagined"] == "1.0"} == {"1", "2", "3"}
    checkpoint = load_checkpoint(tmp_path / "checkpoint.pt")
    assert checkpoint["config"]["imagination"]["fit_every"] == 2


def _rows(folder: Path) -> list[dict[str, str]]:
    with (folder / "metrics.csv").open() as file:
        return list(csv.DictReader(file))


def _learning(rows: list[dict[str, str]], epoch: str) -> list[dict[str, str]]:
    """The epoch's imagined rows without their timings: what the policy learned from and how."""
    return [{key: value for key, value in row.items() if key.startswith(("train/", "imagined/"))}
            for row in rows if row["imagined"] == "1.0" and row["epoch"] == epoch]


@pytest.mark.slow
def test_a_fit_in_the_background_trains_the_policy_on_the_previous_fit_and_resumes_exactly(tmp_path):
    """imagination.background_fit: epoch 2's updates run on epoch 1's model while epoch 2's fit runs
    beside them, so they repeat a run that fits every second epoch; epoch 3's use epoch 2's fit."""
    background_fit = ["imagination.background_fit=true", "world_model.trainer.num_threads=null"]
    background = run_train(*MOE_TINY, "epochs=3", *background_fit, f"hydra.run.dir={tmp_path / 'a'}")
    assert background.returncode == 0, background.stderr
    every_second = run_train(*MOE_TINY, "epochs=3", "imagination.fit_every=2", "world_model.trainer.num_threads=null",
                             f"hydra.run.dir={tmp_path / 'b'}")
    assert every_second.returncode == 0, every_second.stderr
    a, b = _rows(tmp_path / "a"), _rows(tmp_path / "b")
    assert all(row["model/fit_steps"] for row in a if row["imagined"] == "0.0")  # a fit after every epoch
    for epoch in ("1", "2"):
        assert _learning(a, epoch) == _learning(b, epoch) != []
    assert _learning(a, "3") != _learning(b, "3")
    first = run_train(*MOE_TINY, "epochs=2", *background_fit, f"hydra.run.dir={tmp_path / 'c'}")
    assert first.returncode == 0, first.stderr
    resumed = run_train(*MOE_TINY, "epochs=3", *background_fit,
                        f"resume={tmp_path / 'c' / 'checkpoint.pt'}", f"hydra.run.dir={tmp_path / 'd'}")
    assert resumed.returncode == 0, resumed.stderr
    assert_same_training_state(load_checkpoint(tmp_path / "a" / "checkpoint.pt"),
                               load_checkpoint(tmp_path / "d" / "checkpoint.pt"), world_model=True)


@pytest.mark.slow
def test_the_real_rule_keeps_only_the_imagined_updates_the_real_batch_agrees_with(tmp_path):
    result = run_train(*MOE_TINY, "epochs=2", "imagination.stopping.kind=real", "imagination.train_on_real=true",
                       "algo.critic_fit=inline", "imagination.stopping.check_every=1", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    with (tmp_path / "metrics.csv").open() as file:
        real = [row for row in csv.DictReader(file) if row["imagined"] == "0.0"]
    assert len(real) == 2
    for row in real:
        taken, kept = float(row["model/policy_updates"]), float(row["model/kept_updates"])
        assert 1 <= taken <= 4 and 0 <= kept <= taken
        # A rule that stopped early undid the last check's updates; one that ran to the end kept all.
        assert kept == taken or kept == taken - 1
        assert float(row["model/real_surrogate_gain"]) >= 0


# source=moe on robot=grammar: the ensemble conditioned on the morphology, tiny, beside the padded MLP.
GRAMMAR_MOE_TINY = [*TINY, "robot=grammar", "policy=token_mlp", "source=moe", "robot.split.train_size=3",
                    "robot.split.held_out_size=2", "evaluation.every_steps=0", "imagination.steps_per_batch=40",
                    "imagination.horizon.start=4", "imagination.horizon.end=4", "world_model.model.embedding=8",
                    "world_model.model.hidden=[16]", "world_model.model.members=3", "world_model.model.elites=2",
                    "world_model.trainer.max_steps=6", "world_model.trainer.check_every=3",
                    "imagination.stopping.max_updates=2", "imagination.stopping.check_every=1",
                    "imagination.stopping.check_starts=4", "imagination.stopping.check_horizon=3"]


@pytest.mark.slow
def test_a_model_based_grammar_run_trains_on_imagined_tokens_and_resumes_exactly(tmp_path):
    a, b, output = straight_and_resumed(tmp_path, GRAMMAR_MOE_TINY, first=1, total=2)
    assert a["epoch"] == b["epoch"] == 2
    assert a["config"]["world_model"]["model"]["_target_"] == "unipolicy_rl.world_models.TokenEnsemble"
    assert_same_training_state(a, b, world_model=True)
    with (tmp_path / "straight" / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    real = [row for row in rows if row["imagined"] == "0.0"]
    imagined = [row for row in rows if row["imagined"] == "1.0"]
    assert len(real) == 2 and imagined and all(row["imagined/reward_per_step"] for row in imagined)
    assert real[0]["model/validation_mse"] and float(real[1]["model/fresh_error"]) > 0
    assert (tmp_path / "straight" / "logs" / "se-moe-trpo_seed0").is_dir()
    assert "morphologies 3: walking" in output


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("world_model=nope", "nope"),
        ("world_model.model.members=0", "members must be a positive integer, got 0"),
        ("imagination.horizon.start=0", "horizon.start must be an integer >= 1, got 0"),
        ("imagination.stopping.min_improving_fraction=0", "min_improving_fraction must lie in"),
        ("imagination.fit_every=0", "fit_every must be a positive integer, got 0"),
        ("imagination.background_fit=maybe", "background_fit must be true or false, got 'maybe'"),
        ("imagination.stopping.kind=real", "stopping.kind=real checks the imagined updates against the epoch's "
                                           "real batch"),
        ("imagination.stopping.tolerance=1", "stopping.tolerance=1 applies to stopping.kind=real only"),
    ],
)
def test_bad_model_settings_are_refused_by_the_start_up_validation(override, match):
    # (in this process: train.py composes the same config and validates it first, as the run below shows)
    from hydra import compose, initialize_config_dir

    from unipolicy_rl.validation import validate_config

    with pytest.raises(Exception) as refused:  # Hydra's composition error or validation's ValueError
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            validate_config(compose("config", overrides=[*MOE_TINY, "epochs=1", *override.split()]))
    assert match in str(refused.value)


@pytest.mark.slow  # (a train.py process of about 9 s)
def test_bad_model_settings_stop_the_run_before_it_trains(tmp_path):
    # A background fit with the default's 2 fit threads: refused when the world model is built, before any epoch.
    result = run_train(*MOE_TINY, "epochs=1", "imagination.background_fit=true", f"hydra.run.dir={tmp_path}")
    assert result.returncode != 0
    assert "set world_model.trainer.num_threads=null (got 2)" in result.stderr
    assert not (tmp_path / "metrics.csv").exists()


def test_metrpo_with_a_model_whose_members_are_design_cells_is_refused_by_name():
    # (validate_config is train.py's first step: test_validation runs train.py on a bad override)
    from unipolicy_rl.validation import validate_config

    with pytest.raises(ValueError, match="CellEnsemble's members model different designs"):
        validate_config(composed("source=moe", "world_model=moe_thesis", "imagination.stopping.kind=metrpo"))


@pytest.mark.slow
def test_the_run_is_named_for_the_design_world_model_and_algorithm_that_ran():
    named = {overrides: OmegaConf.create(run_train(*overrides, "--cfg", "job", "--resolve").stdout).run_name
             for overrides in [("source=se",), ("source=moe", "world_model=pce"), ("source=pce", "design=de")]}
    assert list(named.values()) == ["se-trpo", "se-pce-trpo", "de-pce-trpo"]


@pytest.mark.slow
def test_a_run_whose_updates_keep_being_skipped_stops_with_its_checkpoint(tmp_path):
    result = run_train_with(POISON_REWARDS, *TINY, "epochs=50", "checkpoint_every=1", "algo.max_consecutive_skips=3",
                            f"hydra.run.dir={tmp_path}")
    assert result.returncode != 0
    assert "stopping: 3 updates in a row were skipped" in result.stderr
    assert "non-finite" in result.stderr
    assert str(tmp_path / "checkpoint.pt") in result.stderr
    assert load_checkpoint(tmp_path / "checkpoint.pt")["epoch"] == 2  # the epochs before the stop are kept
    with (tmp_path / "metrics.csv").open() as file:
        skips = [float(row["train/consecutive_skips"]) for row in csv.DictReader(file)]
    assert skips == [1.0, 2.0]


@pytest.mark.slow
def test_a_failure_inside_the_loop_shuts_the_worker_processes_down_instead_of_hanging(tmp_path):
    """Worker processes of a MultiSyncCollector keep the interpreter alive on exit unless shut down."""
    fail = ("from unipolicy_rl.objectives.updater import TRPOUpdater\n"
            "def fail(self, batch):\n    raise RuntimeError('injected failure')\n"
            "TRPOUpdater.update = fail")
    result = run_train_with(fail, *TINY, "workers=2", "epochs=5", f"hydra.run.dir={tmp_path}", timeout=120)
    assert result.returncode != 0
    assert "injected failure" in result.stderr


def test_checkpoints_of_the_earlier_layouts_load_in_the_current_one(tmp_path):
    """Format 2 kept the policy and learner parts at the top and a model-based run's model and buffer
    inside the collector's state; format 1 had only the epoch. Both read in the current format."""
    weights = {"actor": {"w": torch.ones(2)}, "critic": {"v": torch.zeros(1)}, "observation_statistics": {},
               "critic_optimizer": {}, "critic_generator": torch.zeros(1), "observation_loc": torch.zeros(18),
               "observation_scale": torch.ones(18)}
    config = {"episodes_per_epoch": 10, "robot": {"episode_length": 100}}
    model_based = {"format": 2, "epoch": 4, "config": config, **weights,
                   "collector": {"real": {"epoch": 4, "real_env_steps": 4000}, "model": {"m": torch.ones(3)},
                                 "buffer": {"b": 1}, "model_fitted_for": 3, "imagined_updates": 40}}
    torch.save(model_based, tmp_path / "model_based.pt")
    state = load_checkpoint(tmp_path / "model_based.pt")
    assert state["format"] == 4 and state["collector"] == {"epoch": 4, "real_env_steps": 4000}
    assert torch.equal(state["world_model"]["m"], torch.ones(3)) and state["replay_buffer"] == {"b": 1}
    assert state["model_phase_skipped"]  # written before epoch 4's model fit
    assert torch.equal(state["policy"]["actor"]["w"], state["learner"]["actor"]["w"])
    torch.save({"epoch": 2, "config": config, **weights}, tmp_path / "format1.pt")
    assert load_checkpoint(tmp_path / "format1.pt")["collector"] == {"epoch": 2, "real_env_steps": 2000}
