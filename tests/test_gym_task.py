"""env=gym: a gymnasium task as train.py runs it. The policy's [-1, 1] box is the task's own action
range, the known rewards match the env's, episodes are counted where they end, every learner and
source runs, and what has no meaning on a gym task is refused by name."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from torchrl.envs import GymEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from unipolicy_rl.checkpoint import load_policy
from unipolicy_rl.collectors import TransitionBuffer
from unipolicy_rl.env_factories import gym_task
from unipolicy_rl.envs.gym_task import (
    GymTask,
    evaluate_returns,
    gym_episode_metrics,
    make_gym_env,
    world_model_reward,
    world_model_termination,
)
from unipolicy_rl.factories import make_collector
from unipolicy_rl.settings import make_dynamics_model
from unipolicy_rl.validation import validate_config
from unipolicy_rl.world_models import ClosedFormTrainer

ROOT = Path(__file__).resolve().parents[1]
mujoco = pytest.importorskip("mujoco", reason="env=gym on MuJoCo tasks needs gymnasium[mujoco]")


def composed(*overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=["env=gym", *overrides])


def test_the_gym_env_passes_torchrl_s_checks_and_acts_in_the_unit_box():
    for env_id in ("Pendulum-v1", "InvertedPendulum-v5", "Hopper-v5"):
        env = make_gym_env(env_id=env_id)
        check_env_specs(env)
        assert env.action_spec.space.low.eq(-1).all() and env.action_spec.space.high.eq(1).all()
        assert env.observation_spec["observation"].dtype == torch.float32  # (MuJoCo observes in float64)


def test_the_unit_box_is_the_task_s_own_range_and_beyond_it_is_clipped():
    # Pendulum's torque is in [-2, 2]: the policy's 0.5 is a torque of 1, its 3 the env's clip at 2.
    for policy_action, torque in ((0.5, 1.0), (-1.0, -2.0), (3.0, 2.0)):
        ours, raw = make_gym_env(env_id="Pendulum-v1"), GymEnv("Pendulum-v1")
        ours.set_seed(3), raw.set_seed(3)
        a, b = ours.reset(), raw.reset()
        torch.testing.assert_close(a["observation"], b["observation"].float())
        a["action"], b["action"] = torch.tensor([policy_action]), torch.tensor([torque])
        torch.testing.assert_close(ours.step(a)["next", "observation"], raw.step(b)["next", "observation"].float())


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "InvertedPendulum-v5"])
def test_the_known_reward_on_the_policy_s_actions_is_the_env_s_reward(env_id):
    env = make_gym_env(env_id=env_id)
    env.set_seed(0)
    torch.manual_seed(0)
    # Actions past the box too: the env clips them, and so must the reward's torque cost.
    batch = env.rollout(300, lambda td: td.set("action", 3 * torch.rand(1) - 1.5), break_when_any_done=False)
    task = gym_task(composed(f"env.id={env_id}"))
    assert task.reward_source == "known"
    predicted = world_model_reward(task)(batch.exclude(("next", "reward")).clone())
    torch.testing.assert_close(predicted["next", "reward"], batch["next", "reward"])


def test_the_task_s_reward_and_termination_are_known_or_learned_as_configured():
    hopper = gym_task(composed("env.id=Hopper-v5"))
    assert (hopper.reward_source, hopper.termination_source, hopper.learned_heads()) == ("learned", "known", ["reward"])
    assert world_model_termination(hopper) is not None
    pendulum = gym_task(composed())
    assert (pendulum.reward_source, pendulum.termination_source) == ("known", "none")
    assert world_model_termination(pendulum) is None
    assert gym_task(composed("env.reward=learned", "env.termination=learned")).learned_heads() == \
        ["reward", "terminated"]
    model = make_dynamics_model(composed("source=moe", "env.id=Hopper-v5"), device="meta")
    assert model.learned_outputs == ("reward",)
    assert gym_task(composed("env.id=Hopper-v5")).levels == (1000.0, 2500.0, 3000.0)
    assert gym_task(composed()).levels == (-200.0,)


def test_a_gym_task_s_pce_predicts_held_out_steps_with_its_full_basis_where_the_walker_s_fails():
    # A pendulum's next angle is its angle turned by its rate: a product of two state inputs, which
    # the walker's basis (interactions only through an action) cannot express.
    env = make_gym_env(env_id="Pendulum-v1")
    env.set_seed(0)
    torch.manual_seed(0)
    fitting, held_out = (env.rollout(n, break_when_any_done=False) for n in (2000, 500))
    errors = {}
    for basis in ((), ("world_model.model.truncation=hyperbolic", "world_model.model.interactions=controls")):
        cfg = composed("source=pce", "device=cpu", *basis)
        model = make_dynamics_model(cfg)
        buffer = TransitionBuffer.for_model(3000, model)
        buffer.extend(fitting, 1)
        ClosedFormTrainer(validation_fraction=0.2, oversampling=2.0).fit(model, buffer.contents())
        test = TransitionBuffer.for_model(500, model)
        test.extend(held_out, 1)
        steps = test.contents()
        predicted = model.predict(steps["state"], steps["action"], steps["design"],
                                  torch.zeros(len(steps), dtype=torch.long), deterministic=True)
        change = (steps["next_state"] - steps["state"]).var(0)
        errors[basis] = ((predicted - steps["next_state"]).pow(2).mean(0) / change).mean().item()
    full, walkers = errors.values()
    assert composed("source=pce").world_model.model.interactions == "all"  # what env=gym selects
    assert full < 1e-2 < 0.1 < walkers  # measured: 2e-4 against 0.45


def test_an_epoch_s_returns_count_the_episodes_that_ended_not_the_one_the_epoch_cut():
    cfg = composed("env.frames_per_epoch=300")
    policy = lambda td: td.set("action", torch.zeros(1))  # noqa: E731
    collector = make_collector(cfg, policy, epochs=1)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.shape == torch.Size([1, 300])
    first_episode = batch["next", "reward"][0, :200].sum().item()  # Pendulum: 200 steps, then the epoch cuts
    metrics = gym_episode_metrics(batch, episode_length=200)
    assert metrics["train/episode_reward"] == pytest.approx(first_episode, rel=1e-5)


def test_the_evaluation_runs_whole_deterministic_episodes():
    actor_calls = []

    def policy(td):
        actor_calls.append(1)
        return td.set("action", torch.zeros(td.batch_size + (1,)))

    returns = evaluate_returns(policy, "Pendulum-v1", episodes=3, seed=0, max_steps=200)
    assert len(returns) == 3 and len(actor_calls) == 600
    assert all(-2000 < value < 0 for value in returns)


@pytest.mark.parametrize(("overrides", "message"), [
    (["source=de"], "design"),
    (["robot=grammar", "robot.split.train_size=3", "robot.split.held_out_size=2"], "robot=grammar"),
    (["workers=2", "episodes_per_epoch=2"], "workers=2"),
    (["env.frames_per_epoch=0"], "env.frames_per_epoch"),
    (["env.id=CartPole-v1"], "discrete action"),
    (["env.id=NoSuchTask-v0"], "NoSuchTask-v0"),
    (["env.reward=known", "env.id=Hopper-v5"], "env.reward=known"),
    (["source=pce", "env.reward=learned"], "learns no reward"),
    (["source=moe", "world_model.model.learn=[terminated]"], "world_model.model.learn"),
])
def test_what_has_no_meaning_on_a_gym_task_is_refused_by_name(overrides, message):
    with pytest.raises(ValueError, match=message):
        cfg = composed(*overrides)
        validate_config(cfg)
        from unipolicy_rl.factories import probe_dimensions
        probe_dimensions(cfg)


def test_a_task_s_numbers_are_checked_where_it_is_built():
    with pytest.raises(ValueError, match="positive integer"):
        GymTask("Pendulum-v1", 1000, "auto", "auto", 0, (-200.0,))


QUICK_MODEL = ["world_model.model.hidden=[16]", "world_model.trainer.max_epochs=1", "imagination.steps_per_batch=200",
               "world_model.model.members=2", "world_model.model.elites=1"]


@pytest.mark.parametrize("run", [
    ["source=moe", *QUICK_MODEL],
    # (whole runs of about 15 s each: the slow suite's; ME-TRPO's run above stays in the fast one)
    pytest.param(["source=moe", "algo=sac", "algo.learning_starts=100", "algo.actor_hidden=[16]",
                  "algo.critic_hidden=[16]", *QUICK_MODEL], marks=pytest.mark.slow),
    pytest.param(["source=pce", "world_model.model.order=1"], marks=pytest.mark.slow),
])
def test_train_py_runs_a_gym_task_and_reports_its_returns(tmp_path, run):
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), "env=gym", "env.id=Pendulum-v1", *run,
                             "epochs=2", "env.frames_per_epoch=200", "evaluation.every_steps=200",
                             "env.evaluation_episodes=2", "progress_bar=false", f"hydra.run.dir={tmp_path}"],
                            cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "2 episodes: mean return" in result.stdout
    with open(tmp_path / "metrics.csv") as file:
        rows = [row for row in csv.DictReader(file) if row["eval/mean_return"]]
    assert [float(row["real_env_steps"]) for row in rows] == [200.0, 400.0]
    assert all(-2000 < float(row["eval/mean_return"]) < 0 for row in rows)
    with open(tmp_path / "evaluation" / "returns.csv") as file:
        assert len(list(csv.DictReader(file))) == 2
    # The saved policy rebuilds from its checkpoint and drives the task it trained on.
    loaded = load_policy(tmp_path / "checkpoint.pt")
    env = loaded.env_class(1, **loaded.env_kwargs)
    start = env.reset()
    assert loaded.act(start["observation"].numpy()).shape == (1,)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        acted = loaded.policy(start)
        step = env.step(acted)
    env.close()
    assert torch.allclose(acted["action"], torch.as_tensor(loaded.act(start["observation"].numpy())))
    assert torch.isfinite(step["next", "reward"]).all()
