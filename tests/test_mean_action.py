"""collector.mean_action_robots: the first robots of each real epoch act with the policy's mean
action, the rest sample as they would without it; and the settings it cannot serve are refused."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from test_train import MOE_TINY, TINY, run_train
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.collectors.mean_action import MEAN_ACTION, MeanActionRobots
from unipolicy_rl.envs import BatchedWalkerEnv
from unipolicy_rl.factories import make_learner, make_real_collector
from unipolicy_rl.validation import validate_config

ROOT = Path(__file__).resolve().parents[1]


def composed(*overrides: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def moe_policy():
    torch.manual_seed(0)
    return make_learner(composed("source=moe"), 18, 4).policy


@pytest.fixture(scope="module")
def start():
    env = BatchedWalkerEnv(5)
    env.set_seed(0)
    state = env.reset()
    env.close()
    return state


def test_the_first_robots_take_the_mean_action_and_the_rest_sample_as_they_would_without_it(start):
    policy = moe_policy()
    with torch.no_grad():
        torch.manual_seed(1)
        plain = policy(start.clone())
        torch.manual_seed(1)
        mixed = MeanActionRobots(policy, 2)(start.clone())
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            mean = policy(start.clone())["action"]
    torch.testing.assert_close(mixed["action"][:2], mean[:2])
    assert torch.equal(mixed["action"][2:], plain["action"][2:])  # the same noise, drawn for every row
    assert not torch.allclose(mixed["action"][2:], mean[2:])
    assert mixed[MEAN_ACTION].squeeze(-1).tolist() == [True, True, False, False, False]


def test_with_exploration_off_every_robot_takes_the_mean_action(start):
    policy = moe_policy()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        mixed = MeanActionRobots(policy, 2)(start.clone())
        mean = policy(start.clone())["action"]
    torch.testing.assert_close(mixed["action"], mean)
    assert mixed[MEAN_ACTION].all()


def test_a_batch_with_no_robot_left_to_sample_is_refused(start):
    with pytest.raises(ValueError, match="more rows than that"):
        MeanActionRobots(moe_policy(), 5)(start.clone())
    with pytest.raises(ValueError, match="positive integer"):
        MeanActionRobots(moe_policy(), 0)


def test_a_model_based_run_collects_its_first_robots_with_the_mean_action():
    cfg = composed(*TINY, "source=moe", "workers=1", "episodes_per_epoch=4", "epochs=1",
                   "collector.mean_action_robots=1")
    validate_config(cfg)
    torch.manual_seed(0)
    policy = make_learner(cfg, 18, 4).policy
    with make_real_collector(cfg, policy, full_state=True) as collector:
        batch = next(iter(collector))
    assert batch[MEAN_ACTION][:, :, 0].tolist() == [[True] * 10] + [[False] * 10] * 3  # [robots, steps]
    torch.testing.assert_close(batch["action"][0], batch["loc"][0])
    assert (batch["action"][1:] - batch["loc"][1:]).abs().min() > 0


def test_train_py_runs_a_model_based_run_with_mean_action_robots(tmp_path):
    result = run_train(*MOE_TINY, "episodes_per_epoch=4", "collector.mean_action_robots=1", "epochs=2",
                       f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert (tmp_path / "checkpoint.pt").exists()


@pytest.mark.parametrize(("overrides", "message"), [
    (["env=gym", "env.id=Pendulum-v1", "source=moe"], "env=gym runs one env"),
    (["source=moe", "episodes_per_epoch=4"], "leaves no robot of episodes_per_epoch=4"),
    (["source=moe", "workers=2"], "set workers=1"),
    (["workers=1"], "algo=trpo on the real env"),
    (["source=moe", "imagination.train_on_real=true", "algo.critic_fit=inline"], "imagination.train_on_real=true"),
])
def test_what_the_mean_action_robots_cannot_serve_is_refused_by_name(overrides, message):
    robots = 4 if "episodes_per_epoch=4" in overrides else 1
    cfg = composed(*overrides, f"collector.mean_action_robots={robots}")
    with pytest.raises(ValueError, match=message):
        validate_config(cfg)


@pytest.mark.parametrize("overrides", [["source=moe"], ["algo=sac", "workers=1"], ["source=moe", "algo=sac"]])
def test_a_model_source_or_an_off_policy_learner_takes_them(overrides):
    validate_config(composed(*overrides, "collector.mean_action_robots=2"))
