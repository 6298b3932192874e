"""algo=distill: DAgger from a specialist per morphology into one token policy (learners/distillation.py)."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from test_train import load_checkpoint, load_policy, run_train, straight_and_resumed

from unipolicy_rl.checkpoint import CHECKPOINT_FORMAT, save_checkpoint
from unipolicy_rl.env_factories import morphology_env_kwargs
from unipolicy_rl.envs import MorphologyWalkerEnv
from unipolicy_rl.envs.tokens import ACTION_MASK, MORPHOLOGY
from unipolicy_rl.factories import make_learner, probe_dimensions
from unipolicy_rl.learners.base import policy_state
from unipolicy_rl.learners.distillation import DistillationSettings, SpecialistTeachers
from unipolicy_rl.policy import make_token_actor
from unipolicy_rl.token_statistics import TokenObservationStatistics
from unipolicy_rl.validation import validate_config

CONF = Path(__file__).resolve().parents[1] / "conf"
SPLIT = ["robot=grammar", "robot.split.train_size=2", "robot.split.held_out_size=1"]


def config(*overrides: str):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=[*SPLIT, *overrides])


def write_teacher(path: Path, *overrides: str, seed: int = 0, gain: float = 200.0,
                  policy: str = "token_mlp") -> Path:
    """A specialist's checkpoint as training writes it (by default a padded-MLP policy on one robot),
    with random weights whose last layer is scaled by ``gain``, so its actions span the env's range."""
    cfg = config(f"policy={policy}", *overrides)
    dims = probe_dimensions(cfg)
    torch.manual_seed(seed)
    actor = make_token_actor(cfg, *dims)
    with torch.no_grad():
        last = [module for module in actor.modules() if isinstance(module, torch.nn.Linear)][-1]
        last.weight.mul_(gain)
    state = {"format": CHECKPOINT_FORMAT, "epoch": 1, "elapsed": 0.0, "resumable": False, "best_evaluation": None,
             "config": OmegaConf.to_container(cfg), "observation_dim": dims[0], "action_dim": dims[1],
             "policy": policy_state(actor, TokenObservationStatistics(dims[0]))}
    return save_checkpoint(path, state)


@pytest.fixture(scope="module")
def teachers(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("teachers")
    return [write_teacher(folder / f"train{index}.pt", f"robot.specialist={index}", seed=index) for index in (0, 1)]


def rollout(env: MorphologyWalkerEnv, policy, steps: int = 25):
    with torch.no_grad():
        return env.rollout(steps, policy, break_when_any_done=False)


def test_each_step_is_labelled_with_its_own_robot_s_specialist_action(teachers):
    cfg = config("policy=token_modular", "algo=distill", f"algo.teachers=[{teachers[1]},{teachers[0]}]",
                 "robot.sampling=balanced")
    learner = make_learner(cfg, *probe_dimensions(cfg))
    env = MorphologyWalkerEnv(4, **{**morphology_env_kwargs(cfg), "episode_length": None})
    env.set_seed(0)
    batch = rollout(env, learner.policy, steps=10)
    env.close()
    assert set(batch[MORPHOLOGY].unique().tolist()) == {0, 1}
    labels = learner.teachers.actions(batch)  # (teachers given in any order: matched by their robot)
    for index, path in enumerate(teachers):
        rows = batch[MORPHOLOGY].squeeze(-1) == index
        own = load_policy(path).policy(batch[rows].exclude("action", "loc", "scale", "sample_log_prob"))
        real = batch[ACTION_MASK][rows]
        torch.testing.assert_close(labels[rows][real], own["loc"].clamp(-1, 1)[real])
        assert (labels[rows][~real] == 0).all()
    assert labels.abs().max() > 0.5 and (labels.abs() <= 1).all()  # large actions, clipped as the env clips


@pytest.mark.slow
def test_the_student_learns_its_teachers_actions_on_states_it_has_not_trained_on(tmp_path):
    # Teachers the student can represent (its own architecture, one network for both robots), so
    # what is tested is the DAgger loop: label, aggregate, regress, on the student's own states.
    teachers = [write_teacher(tmp_path / f"train{index}.pt", f"robot.specialist={index}", gain=30.0,
                              policy="token_modular") for index in (0, 1)]
    torch.manual_seed(0)
    cfg = config("policy=token_modular", "algo=distill", f"algo.teachers=[{teachers[0]},{teachers[1]}]",
                 "algo.updates_per_epoch=150", "algo.batch_size=128", "robot.sampling=balanced")
    learner = make_learner(cfg, *probe_dimensions(cfg))
    env = MorphologyWalkerEnv(4, **{**morphology_env_kwargs(cfg), "episode_length": None})
    env.set_seed(0)
    batch = rollout(env, learner.policy)
    assert learner.teachers.actions(batch).abs().max() > 0.3
    gaps = []
    for _ in range(4):  # DAgger rounds
        metrics = learner.update(batch)
        learner.refresh_observation_normalizer(batch)
        gaps.append(metrics["distill/teacher_gap"])  # on the epoch's states, before its own steps
        batch = rollout(env, learner.policy)
    env.close()
    assert gaps[-1] < 0.1 * gaps[0], gaps
    assert metrics["distill/gradient_steps"] == 4 * 150 and metrics["distill/buffer_size"] == 4 * 100


def test_a_normaliser_refresh_leaves_the_student_s_actions_as_they_were(teachers):
    cfg = config("policy=token_modular", "algo=distill", f"algo.teachers=[{teachers[0]},{teachers[1]}]")
    learner = make_learner(cfg, *probe_dimensions(cfg))
    env = MorphologyWalkerEnv(2, **{**morphology_env_kwargs(cfg), "episode_length": None})
    env.set_seed(1)
    batch = rollout(env, learner.policy, steps=10)
    env.close()
    assert learner.refresh_observation_normalizer(batch)["distill/refresh_max_mean_change"] < 1e-4
    assert not torch.equal(learner.normalizer.loc, torch.zeros_like(learner.normalizer.loc))  # it did move


def test_teachers_that_do_not_fit_the_student_are_refused_by_name(teachers, tmp_path):
    cfg = config("policy=token_modular")
    kwargs = morphology_env_kwargs(cfg)
    with pytest.raises(ValueError, match=r"no specialist for morphologies \[1\]"):
        SpecialistTeachers(kwargs, [teachers[0]])
    with pytest.raises(ValueError, match="both teach morphology 0"):
        SpecialistTeachers(kwargs, [teachers[0], teachers[0]])
    universal = write_teacher(tmp_path / "universal.pt")
    with pytest.raises(ValueError, match="universal.pt is not a specialist's checkpoint"):
        SpecialistTeachers(kwargs, [universal, *teachers])
    held_out = write_teacher(tmp_path / "held_out.pt", "robot.morphologies=held_out", "robot.specialist=0")
    with pytest.raises(ValueError, match="held_out.pt's robot is none of the 2 morphologies the student trains on"):
        SpecialistTeachers(kwargs, [held_out, *teachers])
    stronger = write_teacher(tmp_path / "stronger.pt", "robot.specialist=0", "robot.physics.max_torque=3.0")
    with pytest.raises(ValueError, match="stronger.pt ran with another physics"):
        SpecialistTeachers(kwargs, [stronger, teachers[1]])
    with pytest.raises(ValueError, match="algo.teachers is empty"):
        DistillationSettings(teachers=())
    with pytest.raises(ValueError, match="algo.teachers: no checkpoint at 'missing.pt'"):
        SpecialistTeachers(kwargs, ["missing.pt", *teachers])
    with pytest.raises(ValueError, match="algo.updates_per_epoch must be an integer >= 1, got 0"):
        DistillationSettings(teachers=(str(teachers[0]),), updates_per_epoch=0)


@pytest.mark.parametrize(("overrides", "message"), [
    (["algo=distill"], "algo=distill teaches a token policy the specialists of robot=grammar's morphologies"),
    ([*SPLIT, "policy=token_modular", "algo=distill", "source=moe"], "algo=distill labels the student's real steps"),
    ([*SPLIT, "policy=token_modular", "algo=distill"], "algo.teachers is empty"),
    ([*SPLIT, "policy=token_modular", "algo=distill", "algo.teachers=[a.pt]", "algo.learning_rate=0"],
     "algo.learning_rate must be positive, got 0"),
])
def test_a_distillation_that_cannot_run_is_refused_at_start_up(overrides, message):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    with pytest.raises(ValueError, match=message):
        validate_config(cfg)


@pytest.mark.slow
def test_a_distillation_run_trains_evaluates_and_resumes_exactly(teachers, tmp_path):
    overrides = [*SPLIT, "policy=token_modular", "algo=distill", f"algo.teachers=[{teachers[0]},{teachers[1]}]",
                 "episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false",
                 "evaluation.every_steps=1", "evaluation.morphology_grid=1", "algo.updates_per_epoch=5",
                 "algo.batch_size=8"]
    a, b, _ = straight_and_resumed(tmp_path, overrides, first=1, total=2)
    assert a["epoch"] == b["epoch"] == 2
    for key, value in a["learner"]["actor"].items():
        assert torch.equal(value, b["learner"]["actor"][key]), f"actor.{key} differs after resume"
    assert a["learner"]["gradient_steps"] == b["learner"]["gradient_steps"] == 10
    stored = a["learner"]["buffer"]["_storage"]["_storage"]
    assert all(torch.equal(value, b["learner"]["buffer"]["_storage"]["_storage"][key])
               for key, value in stored.items())
    # The distilled policy loads and runs as any token policy.
    loaded = load_policy(tmp_path / "straight" / "checkpoint.pt")
    assert loaded.env_class is MorphologyWalkerEnv
    assert load_checkpoint(tmp_path / "straight" / "checkpoint.pt")["config"]["algo"]["name"] == "distill"
    # A teacher missing from the folder it was given in stops the run at start-up, naming it.
    failed = run_train(*overrides[:3], f"algo.teachers=[{teachers[0]},{tmp_path / 'gone.pt'}]", "epochs=1",
                       f"hydra.run.dir={tmp_path / 'failed'}")
    assert failed.returncode != 0 and "gone.pt" in failed.stderr
