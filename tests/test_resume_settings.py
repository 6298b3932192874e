"""What a resume restores and what its command line may change, and the paths that once went silent
or raw: each refused before any work, naming the key and the values allowed. Fast: configs are
composed as train.py composes them, nothing trains."""

import csv
import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf, open_dict

from unipolicy_rl.checkpoint import CHECKPOINT_FORMAT, load_checkpoint, save_checkpoint
from unipolicy_rl.resume import named_keys, settings_for_resume, with_the_runs_groups

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


# ---------------------------------------------------------------------- composing as train.py does
def composed_run(arguments: list[str], folder: Path):
    """The config train.py composes from ``arguments`` (Hydra's node set, as inside a run), its group
    choices and the command line's overrides."""
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=arguments, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(folder)
    HydraConfig.instance().set_config(cfg)
    choices = {group: choice for group, choice in cfg.hydra.runtime.choices.items() if not group.startswith("hydra/")}
    task = list(cfg.hydra.overrides.task)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg, choices, task


def checkpoint_of(folder: Path, *overrides: str, format_3: bool = False) -> Path:
    """A run's checkpoint as train.py saves it (its resolved config and group choices), weights aside."""
    cfg, choices, _ = composed_run(list(overrides), folder)
    state = {"format": CHECKPOINT_FORMAT, "epoch": 1, "elapsed": 0.0,
             "config": OmegaConf.to_container(cfg, resolve=True), "choices": choices,
             "observation_dim": 18, "action_dim": 4, "policy": {}}
    if format_3:
        state = {key: value for key, value in state.items() if key != "choices"} | {"format": 3}
    return save_checkpoint(folder / "checkpoint.pt", state)


def resumed(checkpoint: Path, *command_line: str):
    """The config ``python train.py resume=<checkpoint> <command_line>`` runs with."""
    arguments = with_the_runs_groups(["train.py", *command_line, f"resume={checkpoint}"], CONF)[1:]
    cfg, choices, task = composed_run(arguments, checkpoint.parent / "resumed")
    return settings_for_resume(cfg, load_checkpoint(checkpoint), named_keys(task, choices), choices, checkpoint)


def resume_lines(printed: str) -> list[str]:
    return [line for line in printed.splitlines() if line.startswith("resume:")]


# ---------------------------------------------------------------------- a resume is the run it was
def test_a_model_based_run_extended_on_the_command_line_keeps_its_source_and_its_interpolated_settings(tmp_path,
                                                                                                        capsys):
    checkpoint = checkpoint_of(tmp_path, "source=moe", "algo.critic_fit=inline", "seed=2", "world_model=moe_thesis")
    cfg = resumed(checkpoint, "epochs=100")
    assert (cfg.source.name, cfg.seed, cfg.epochs) == ("moe", 2, 100)
    assert cfg.algo.critic_fit == "inline"  # an interpolation in today's config, set by the run
    assert cfg.world_model.model._target_.endswith("CellEnsemble")
    assert resume_lines(capsys.readouterr().out) == []  # source=moe's epochs are 100: nothing changes


@pytest.mark.parametrize(("overrides", "expected"), [
    (["algo=sac", "algo.learning_rate=0.001", "algo.learning_starts=50", "evaluation.every_steps=400"],
     {"algo.name": "sac", "algo.learning_rate": 0.001, "algo.learning_starts": 50, "evaluation.every_steps": 400}),
    (["algo=ppo", "algo.clip_epsilon=0.1", "algo.policy_epochs=3"],
     {"algo.name": "ppo", "algo.clip_epsilon": 0.1, "algo.policy_epochs": 3}),
    (["algo=crossq", "algo.actor_update_every=2"],
     {"algo.name": "crossq", "algo.target_update_rate": None, "algo.actor_update_every": 2}),
    (["algo=redq", "algo.num_critics=4"], {"algo.name": "redq", "algo.num_critics": 4, "algo.updates_per_step": 20}),
    (["robot=grammar", "policy=token_modular", "algo=distill", "algo.teachers=[a.pt,b.pt]"],
     {"algo.name": "distill", "algo.teachers": ["a.pt", "b.pt"], "policy.name": "token_modular",
      "robot.kind": "grammar"}),
])
def test_a_resume_from_the_checkpoint_alone_restores_every_setting_of_the_run(overrides, expected, tmp_path, capsys):
    cfg = resumed(checkpoint_of(tmp_path, *overrides))
    assert {key: OmegaConf.to_container(value) if OmegaConf.is_config(value := OmegaConf.select(cfg, key)) else value
            for key in expected} == expected
    assert resume_lines(capsys.readouterr().out) == []  # nothing changed, nothing said


def test_the_command_line_changes_what_it_names_and_each_change_is_printed(tmp_path, capsys):
    checkpoint = checkpoint_of(tmp_path, "algo=ppo", "algo.clip_epsilon=0.1", "epochs=7")
    cfg = resumed(checkpoint, "algo=ppo", "algo.max_grad_norm=0.25")  # naming the run's own choice changes nothing
    assert (cfg.algo.clip_epsilon, cfg.algo.max_grad_norm, cfg.epochs) == (0.1, 0.25, 7)
    assert resume_lines(capsys.readouterr().out) == ["resume: algo.max_grad_norm: 0.5 -> 0.25"]


def test_a_run_folder_is_named_after_the_resumed_run(tmp_path):
    checkpoint = checkpoint_of(tmp_path, "source=de", "algo=ppo", "seed=3")
    arguments = with_the_runs_groups(["train.py", "epochs=9", f"resume={checkpoint}"], CONF)
    assert arguments[0:2] == ["train.py", "epochs=9"] and arguments[-1] == f"resume={checkpoint}"
    assert {"source=de", "algo=ppo", "design=de", "seed=3"} <= set(arguments)
    # What the command line names itself is not added again.
    assert with_the_runs_groups(["train.py", "seed=5", f"resume={checkpoint}"], CONF).count("seed=5") == 1


@pytest.mark.parametrize(("command_line", "message"), [
    (["algo=sac"], "algo=sac here, algo=ppo in the checkpoint"),
    (["robot=grammar", "policy=token_mlp"], "robot=grammar here, robot=vertebrate in the checkpoint"),
    (["algo.actor_hidden=[8]"], r"algo.actor_hidden: \[8\] here, \[64, 64\] in the checkpoint"),
    (["source=moe"], "source=moe here, source=se in the checkpoint"),
])
def test_what_a_resume_cannot_change_is_refused_by_name(command_line, message, tmp_path):
    checkpoint = checkpoint_of(tmp_path, "algo=ppo")
    with pytest.raises(ValueError, match=message):
        resumed(checkpoint, *command_line)


def test_a_setting_newer_than_the_checkpoint_takes_todays_default_and_says_so(tmp_path, capsys):
    checkpoint = checkpoint_of(tmp_path, "algo.max_kl=0.03")
    state = torch.load(checkpoint, weights_only=False)
    del state["config"]["algo"]["max_consecutive_skips"]
    save_checkpoint(checkpoint, state)
    cfg = resumed(checkpoint)
    assert cfg.algo.max_kl == 0.03
    default = cfg.algo.max_consecutive_skips
    assert resume_lines(capsys.readouterr().out) == [f"resume: algo.max_consecutive_skips={default}: newer than the "
                                                     "checkpoint, this version's default"]


def test_a_config_from_before_a_setting_gets_what_its_run_did_not_today_s_default(tmp_path, capsys):
    # critic_fit: today a MOE run fits its critic in a second process; before the setting, inline.
    checkpoint = checkpoint_of(tmp_path, "source=moe")
    state = torch.load(checkpoint, weights_only=False)
    for key in ("critic_fit", "fisher_fraction", "advantage_groups"):
        del state["config"]["algo"][key]
    del state["config"]["env"]
    save_checkpoint(checkpoint, state)
    config = load_checkpoint(checkpoint)["config"]
    assert (config["algo"]["critic_fit"], config["algo"]["fisher_fraction"], config["algo"]["advantage_groups"],
            config["env"]) == ("inline", 1.0, None, {"kind": "walker"})
    cfg = resumed(checkpoint)
    assert cfg.algo.critic_fit == "inline"
    assert not [line for line in resume_lines(capsys.readouterr().out) if "newer than the checkpoint" in line]


def test_a_checkpoint_from_before_group_choices_were_saved_resumes_with_its_own_groups(tmp_path):
    checkpoint = checkpoint_of(tmp_path, "algo=ppo", "source=de", "algo.clip_epsilon=0.3", format_3=True)
    assert load_checkpoint(checkpoint)["choices"] == {"algo": "ppo", "source": "de", "policy": "mlp",
                                                      "robot": "vertebrate"}
    cfg = resumed(checkpoint)
    assert (cfg.algo.name, cfg.source.name, cfg.algo.clip_epsilon) == ("ppo", "de", 0.3)


# ---------------------------------------------------------------------- REDQ's lazily created buffer
def test_a_redq_loss_after_its_first_step_loads_into_a_fresh_one():
    from unipolicy_rl.learners.off_policy import OffPolicySettings, make_loss, with_lazy_buffers
    from unipolicy_rl.policy import make_policy_actor

    cfg = OmegaConf.create({"algo": {"name": "redq", "actor_hidden": [8], "activation": "relu"},
                            "policy": {"name": "mlp"}})
    settings = OffPolicySettings(loss="redq", num_critics=3, critic_hidden=(8,))
    trained = make_loss(settings, make_policy_actor(cfg, 5, 2), 5, 2)
    trained.target_entropy  # noqa: B018 - what its first step reads
    fresh = make_loss(settings, make_policy_actor(cfg, 5, 2), 5, 2)
    fresh.load_state_dict(trained.state_dict())
    assert float(fresh.target_entropy) == -2.0
    before_its_first_step = {key: value for key, value in trained.state_dict().items()
                             if key != "target_entropy_buffer"}
    fresh.load_state_dict(with_lazy_buffers(fresh, before_its_first_step))


# ---------------------------------------------------------------------- metrics.csv after a resume
def write_rows(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def test_a_resumed_run_logs_each_epoch_once_and_the_report_agrees(tmp_path):
    from unipolicy_rl.report.runs import load_run
    from unipolicy_rl.training.metrics_file import EPOCH, FILE_NAME, IMAGINED, REWARD, MetricsCSV

    path = tmp_path / FILE_NAME
    # Checkpoint at epoch 2; epoch 3 (an imagined row, then its real row) logged, then killed.
    cut = [{EPOCH: epoch, IMAGINED: imagined, REWARD: reward}
           for epoch, imagined, reward in [(1, 1.0, ""), (1, 0.0, 1.0), (2, 1.0, ""), (2, 0.0, 2.0), (3, 1.0, ""),
                                           (3, 0.0, 3.0)]]
    write_rows(path, cut)
    # The report reads the epoch the resume redoes once, the later row (here, a file both appended to) ...
    write_rows(tmp_path / "both.csv", [*cut, {EPOCH: 3, IMAGINED: 1.0, REWARD: ""}, {EPOCH: 3, IMAGINED: 0.0,
                                                                                    REWARD: 3.5}])
    (tmp_path / "both").mkdir()
    (tmp_path / "both.csv").rename(tmp_path / "both" / FILE_NAME)
    rows = load_run(tmp_path / "both", "both").rows
    assert [(row[EPOCH], row[IMAGINED]) for row in rows] == [(1, 1), (1, 0), (2, 1), (2, 0), (3, 1), (3, 0)]
    assert rows[-1][REWARD] == 3.5
    # ... and the resumed run's file holds it once: the rows after its checkpoint go when it starts.
    MetricsCSV(path).drop_epochs_after(2)
    with path.open(newline="") as file:
        assert [(row[EPOCH], row[IMAGINED]) for row in csv.DictReader(file)] == [("1", "1.0"), ("1", "0.0"),
                                                                                ("2", "1.0"), ("2", "0.0")]


# ---------------------------------------------------------------------- silent and raw paths
def composed(*overrides: str):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize(("settings", "message"), [
    ({"buffer_capacity": 100, "learning_starts": 150},
     r"algo.learning_starts \(150\) must not exceed algo.buffer_capacity \(100\)"),
    ({"adam_betas": (0.9,)}, r"algo.adam_betas must be two numbers in \[0, 1\)"),
    ({"adam_betas": (0.9, 1.0)}, r"algo.adam_betas must be two numbers in \[0, 1\)"),
    ({"alpha_init": -1.0}, "algo.alpha_init .* must be a positive number, got -1.0"),
    ({"alpha_init": 0.0}, "algo.alpha_init .* must be a positive number, got 0.0"),
])
def test_off_policy_settings_that_could_never_learn_are_refused_by_key(settings, message):
    from unipolicy_rl.learners.off_policy import OffPolicySettings

    with pytest.raises(ValueError, match=message):
        OffPolicySettings(**settings)


@pytest.mark.parametrize(("overrides", "message"), [
    (["world_model=pce_sparse"], "world_model is read by a model-based source only, and source=se"),
    (["imagination=branch"], "imagination is read by a model-based source only, and source=se"),
    (["algo=sac", "imagination=branch"], "imagination is read by a model-based source only"),
])
def test_a_world_model_or_imagination_with_a_real_source_is_refused(overrides, message):
    from unipolicy_rl.validation import check_settings

    with pytest.raises(ValueError, match=message):
        check_settings(composed(*overrides), "source", "world_model", "imagination", "algo.name")
    # An off-policy learner's own imagination (MBPO's) goes with it whatever the source.
    check_settings(composed("algo=sac", "imagination=mbpo"), "source", "world_model", "imagination", "algo.name")


def test_a_polynomial_chaos_model_of_order_zero_is_refused():
    from unipolicy_rl.factories import make_dynamics_model

    with pytest.raises(ValueError, match="order must be an integer >= 1 .* got 0"):
        make_dynamics_model(composed("source=pce", "world_model=pce_sparse", "world_model.model.order=0"),
                            device="meta")


def test_ppo_names_its_config_keys():
    from unipolicy_rl.objectives import ClippedSurrogate

    with pytest.raises(ValueError, match="algo.policy_epochs must be a positive integer, got 0"):
        ClippedSurrogate(epochs=0)


def test_robot_slots_and_driven_joints_are_checked_at_start_up_by_their_keys():
    from unipolicy_rl.env_factories import morphology_env_kwargs
    from unipolicy_rl.validation import check_settings

    grammar = ["robot=grammar", "policy=token_mlp", "robot.split.train_size=2", "robot.split.held_out_size=1"]
    with pytest.raises(ValueError, match="robot.max_links=2 token slots are fewer than the .* links"):
        morphology_env_kwargs(composed(*grammar, "robot.max_links=2"))
    with pytest.raises(ValueError, match=r"robot.driven_joints must be a non-empty list of .* got \['bogus'\]"):
        check_settings(composed(*grammar, "robot.driven_joints=[bogus]"), "robot.driven_joints")


def test_ray_names_a_missing_client_and_an_unreachable_cluster(monkeypatch):
    import importlib.util

    from unipolicy_rl.collectors import distributed

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "grpc" else real_find_spec(name))
    with pytest.raises(ImportError, match=r"collector.ray_address=ray://host:10001 .*ray\[client\]"):
        distributed.require_ray("ray://host:10001")

    def no_cluster(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance.")

    monkeypatch.setattr(distributed.EpochRayCollector, "__init__", no_cluster)
    with pytest.raises(ConnectionError, match="collector.ray_address=auto: no Ray cluster answers there"):
        distributed.make_epoch_ray_collector([], None, frames_per_batch=1, total_frames=1, postproc=None,
                                             address="auto")
    assert re.search(r'^ray = \["ray\[client\]', (ROOT / "pyproject.toml").read_text(), re.MULTILINE)


def test_a_run_lock_that_cannot_be_removed_does_not_hide_the_runs_own_error(tmp_path, monkeypatch, capsys):
    from unipolicy_rl.training import RunLock

    def unwritable(self, missing_ok=False):
        raise PermissionError(13, "Permission denied", str(self))

    with pytest.raises(RuntimeError, match="the run's own error"):
        with RunLock(tmp_path):
            monkeypatch.setattr(Path, "unlink", unwritable)
            raise RuntimeError("the run's own error")
    assert "could not remove" in capsys.readouterr().out


def test_evaluating_a_vertebrate_policy_on_morphologies_is_one_clear_error(tmp_path, capsys):
    from unipolicy_rl import evaluate
    from unipolicy_rl.learners.base import policy_state
    from unipolicy_rl.observation_statistics import ObservationStatistics
    from unipolicy_rl.policy import make_policy_actor

    cfg = composed()
    state = {"format": CHECKPOINT_FORMAT, "epoch": 1, "elapsed": 0.0, "resumable": False, "best_evaluation": None,
             "config": OmegaConf.to_container(cfg, resolve=False), "observation_dim": 18, "action_dim": 4,
             "policy": policy_state(make_policy_actor(cfg, 18, 4), ObservationStatistics(18))}
    path = save_checkpoint(tmp_path / "vertebrate.pt", state)
    arguments = [str(path), "--morphologies", "held_out", "--grid", "1"]
    with pytest.raises(ValueError, match="--morphologies held_out chooses among"):
        evaluate.main(arguments)  # called from code, the error is raised
    with pytest.raises(SystemExit) as exit_:
        evaluate.cli(arguments)
    assert exit_.value.code == 1
    error = capsys.readouterr().err
    assert "--morphologies held_out chooses among a robot=grammar policy's morphologies" in error
    assert "Traceback" not in error and len(error.strip().splitlines()) == 1
