"""init_policy: a new run starts from another run's policy (initial_policy.py)."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

from unipolicy_rl.checkpoint import CHECKPOINT_FORMAT, save_checkpoint
from unipolicy_rl.factories import make_learner
from unipolicy_rl.initial_policy import policy_to_start_from

CONF = Path(__file__).resolve().parents[1] / "conf"
DIMS = (18, 4)  # the vertebrate's observation and action sizes


def config(*overrides: str):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def observations(seed: int, batch: tuple[int, ...] = (2, 64)) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(*batch, DIMS[0], generator=generator) * 3.0 + torch.arange(float(DIMS[0]))


def trained_learner_checkpoint(path: Path, *overrides: str) -> tuple[Path, object]:
    """A learner whose policy is not the one a fresh run builds (other weights, its normaliser moved
    to observations far from zero mean and unit scale), saved as training saves a policy."""
    cfg = config(*overrides)
    torch.manual_seed(1)
    learner = make_learner(cfg, *DIMS)
    with torch.no_grad():
        for parameter in learner.actor.parameters():
            parameter.add_(0.3 * torch.randn_like(parameter))
    learner.refresh_observation_normalizer(TensorDict({"observation": observations(0)}, batch_size=[2, 64]))
    state = {"format": CHECKPOINT_FORMAT, "epoch": 3, "elapsed": 0.0, "resumable": False, "best_evaluation": None,
             "config": OmegaConf.to_container(cfg), "observation_dim": DIMS[0], "action_dim": DIMS[1],
             "policy": learner.policy_state()}
    return save_checkpoint(path, state), learner


def actions(learner, seed: int) -> TensorDict:
    probe = TensorDict({"observation": observations(seed, (256,))}, batch_size=[256])
    with torch.no_grad():
        return learner.policy(probe)


def test_a_new_run_acts_as_the_policy_it_starts_from_and_a_refresh_keeps_it_so(tmp_path):
    path, source = trained_learner_checkpoint(tmp_path / "policy.pt")
    cfg = config("algo=ppo")  # another learner with the same actor: PPO fine-tuning TRPO's policy
    torch.manual_seed(2)
    learner = make_learner(cfg, *DIMS)
    expected = actions(source, seed=5)
    assert not torch.allclose(actions(learner, seed=5)["loc"], expected["loc"], atol=1e-3)
    learner.start_from_policy(policy_to_start_from(cfg, path, *DIMS))
    started = actions(learner, seed=5)
    torch.testing.assert_close(started["loc"], expected["loc"])
    torch.testing.assert_close(started["scale"], expected["scale"])
    # its own statistics start empty: the first refresh moves the normaliser to this run's
    # observations and re-expresses the actor, so the policy does not change
    learner.refresh_observation_normalizer(TensorDict({"observation": observations(7) * 0.5}, batch_size=[2, 64]))
    assert not torch.allclose(learner.normalizer.loc, source.normalizer.loc)
    torch.testing.assert_close(actions(learner, seed=5)["loc"], expected["loc"], atol=1e-4, rtol=1e-4)


@pytest.mark.slow
def test_train_py_starts_from_the_policy_and_trains_on(tmp_path):
    from test_train import TINY, load_policy, run_train

    path, source = trained_learner_checkpoint(tmp_path / "policy.pt")
    result = run_train(*TINY, "workers=1", "epochs=1", f"init_policy={path}", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"started from the policy in {path}" in result.stdout
    trained = load_policy(tmp_path / "run" / "checkpoint.pt").policy
    probe = TensorDict({"observation": observations(5, (256,))}, batch_size=[256])
    with torch.no_grad():
        moved = (trained(probe.clone())["loc"] - actions(source, seed=5)["loc"]).abs().mean().item()
        fresh = (make_learner(config(), *DIMS).policy(probe.clone())["loc"] - actions(source, seed=5)["loc"])
    # one TRPO step on from the loaded policy (a KL of at most algo.max_kl): near it, where a fresh actor is far
    assert 0 < moved < fresh.abs().mean().item() / 5


@pytest.mark.parametrize(("overrides", "named"), [
    (["algo.actor_hidden=[32,32]"], "algo.actor_hidden: [32, 32] here, [64, 64] there"),
    (["algo.activation=relu"], "algo.activation: relu here, tanh there"),
    (["algo=sac"], "algo.actor_hidden: [256, 256] here, [64, 64] there"),
])
def test_a_policy_that_does_not_fit_the_run_is_refused_naming_the_setting(tmp_path, overrides, named):
    path, _ = trained_learner_checkpoint(tmp_path / "policy.pt")
    with pytest.raises(ValueError, match="init_policy") as error:
        policy_to_start_from(config(*overrides), path, *DIMS)
    assert named in str(error.value)
    with pytest.raises(ValueError, match=r"observation and action sizes: \(18, 6\) here, \(18, 4\) there"):
        policy_to_start_from(config(), path, 18, 6)


def test_a_missing_or_foreign_file_is_named(tmp_path):
    with pytest.raises(ValueError, match="init_policy: no checkpoint at .*nowhere.pt"):
        policy_to_start_from(config(), tmp_path / "nowhere.pt", *DIMS)
    (tmp_path / "notes.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="init_policy: .*notes.pt.* is not a readable checkpoint"):
        policy_to_start_from(config(), tmp_path / "notes.pt", *DIMS)


def test_weights_of_another_network_are_refused_by_the_learner():
    learner = make_learner(config(), *DIMS)
    other = make_learner(config("algo.actor_hidden=[32,32]"), *DIMS).policy_state()
    with pytest.raises(ValueError, match="init_policy: its actor's weights do not load into this run's actor"):
        learner.start_from_policy(other)
