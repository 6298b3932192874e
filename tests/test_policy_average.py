"""algo.policy_average: an exponential moving average of the actor's weights acts, is evaluated and is
saved, while the learner trains its own weights; off, nothing changes; a resume continues it exactly."""

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from test_train import MOE_TINY, TINY, assert_same_training_state, run_train_with, straight_and_resumed

from unipolicy_rl.checkpoint import load_checkpoint, load_policy
from unipolicy_rl.learners import TRPOLearner
from unipolicy_rl.learners.policy_average import STATE_KEY, AveragedLearner, end_of_epoch, learning_policy

ROOT = Path(__file__).resolve().parents[1]


def composed(*overrides: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def learner(*overrides: str):
    from unipolicy_rl.factories import make_learner

    torch.manual_seed(0)
    return make_learner(composed(*overrides), 18, 4)


def perturb(module: torch.nn.Module, generator: torch.Generator) -> None:
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.add_(torch.randn(parameter.shape, generator=generator))


@pytest.mark.parametrize("decay", [0.5, 0.8])
def test_the_average_after_k_steps_is_the_exponential_moving_average_of_the_weights(decay):
    averaged = learner(f"algo.policy_average.decay={decay}")
    assert isinstance(averaged, AveragedLearner) and isinstance(averaged.learner, TRPOLearner)
    generator = torch.Generator().manual_seed(1)
    history = [{name: value.clone() for name, value in averaged.learner.actor.state_dict().items()}]
    for _ in range(4):
        perturb(averaged.learner.actor, generator)  # what an epoch's updates do
        history.append({name: value.clone() for name, value in averaged.learner.actor.state_dict().items()})
        metrics = end_of_epoch(averaged)
    k = len(history) - 1
    for name, value in averaged.average_actor.state_dict().items():
        # decay^k w_0 + (1 - decay) sum_i decay^(k - i) w_i
        expected = decay**k * history[0][name] + sum((1 - decay) * decay ** (k - i) * history[i][name]
                                                      for i in range(1, k + 1))
        torch.testing.assert_close(value, expected, rtol=1e-5, atol=1e-6)
    assert metrics["policy_average/distance"] > 0
    # The learner's own weights are untouched by the averaging, and they are what imagination trains.
    for name, value in averaged.learner.actor.state_dict().items():
        assert torch.equal(value, history[-1][name])
    assert learning_policy(averaged) is averaged.learner.policy and averaged.policy is not averaged.learner.policy


@pytest.mark.parametrize("decay", ["null", "0"])
def test_off_the_learner_is_the_plain_one(decay):
    plain = learner(f"algo.policy_average.decay={decay}")
    assert type(plain) is TRPOLearner
    assert learning_policy(plain) is plain.policy and end_of_epoch(plain) == {}


@pytest.mark.parametrize(("overrides", "match"), [
    (["algo.policy_average.decay=1.0"], r"algo.policy_average.decay must lie in \[0, 1\)"),
    (["algo.policy_average.decay=-0.5"], r"algo.policy_average.decay must lie in \[0, 1\)"),
    (["algo=sac", "+algo.policy_average.decay=0.5"], "averages an on-policy learner's actor"),
])
def test_bad_decays_are_refused_by_name(overrides, match):
    from unipolicy_rl.validation import validate_config

    with pytest.raises(ValueError, match=match):
        validate_config(composed(*overrides))


def test_a_refresh_leaves_the_acting_policy_unchanged_and_the_checkpoint_holds_the_average():
    averaged = learner("algo.policy_average.decay=0.5")
    perturb(averaged.learner.actor, torch.Generator().manual_seed(2))
    end_of_epoch(averaged)
    observations = torch.randn(2, 32, 18, generator=torch.Generator().manual_seed(3)) * 3 + 1
    probe = TensorDict({"observation": observations.reshape(-1, 18)}, batch_size=[64])
    with torch.no_grad():
        before = averaged.policy(probe.clone())["loc"]
        averaged.refresh_observation_normalizer(TensorDict({"observation": observations}, batch_size=[2, 32]))
        after = averaged.policy(probe.clone())["loc"]
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-5)
    policy = averaged.policy_state()
    for name, value in averaged.average_actor.state_dict().items():
        assert torch.equal(policy["actor"][name], value)
    own = averaged.learner.actor.state_dict()
    assert any(not torch.equal(value, own[name]) for name, value in policy["actor"].items())


def test_the_collector_acts_with_the_average():
    from unipolicy_rl.factories import make_real_collector

    cfg = composed(*TINY, "workers=1", "epochs=1", "algo.policy_average.decay=0.5")
    averaged = learner(*TINY, "workers=1", "algo.policy_average.decay=0.5")
    perturb(averaged.learner.actor, torch.Generator().manual_seed(4))  # the learner has moved, the average not yet
    with make_real_collector(cfg, averaged.policy, full_state=False) as collector:
        batch = next(iter(collector))
    probe = batch.reshape(-1).select("observation")
    with torch.no_grad():
        average = averaged.policy(probe.clone())["loc"]
        own = averaged.learner.policy(probe.clone())["loc"]
    torch.testing.assert_close(batch.reshape(-1)["loc"], average)
    assert not torch.allclose(average, own)


# Each periodic evaluation's policy weights, saved where the test reads them.
RECORD_EVALUATED = """
import torch
from unipolicy_rl.training.progress import PeriodicEvaluation
_call = PeriodicEvaluation.__call__
def recording(self, epoch, steps, policy):
    torch.save({k: v.clone() for k, v in policy.state_dict().items()}, f"RECORD/evaluated{epoch}.pt")
    return _call(self, epoch, steps, policy)
PeriodicEvaluation.__call__ = recording
"""


@pytest.mark.slow
def test_a_model_based_run_acts_evaluates_and_saves_with_the_average_and_resumes_it_exactly(tmp_path):
    overrides = [*MOE_TINY, "algo.policy_average.decay=0.5"]
    a, b, _ = straight_and_resumed(tmp_path, overrides, first=1, total=3)
    assert_same_training_state(a, b, world_model=True)
    for name, value in a["learner"][STATE_KEY].items():
        assert torch.equal(value, b["learner"][STATE_KEY][name]), f"average {name} differs after resume"
        # The run's saved policy is the average, not the learner's own weights.
        assert torch.equal(a["policy"]["actor"][name], value)
    assert any(not torch.equal(value, a["learner"]["actor"][name]) for name, value in a["policy"]["actor"].items())
    loaded = load_policy(tmp_path / "straight" / "checkpoint.pt")
    assert all(torch.equal(value, a["policy"]["actor"][name]) for name, value in
               loaded.policy[1].state_dict().items())


@pytest.mark.slow
def test_the_periodic_evaluation_runs_the_average(tmp_path):
    """Its last one (after the last epoch's averaging step) evaluates the policy the checkpoint saves."""
    record = tmp_path / "record"
    record.mkdir()
    result = run_train_with(RECORD_EVALUATED.replace("RECORD", str(record)), *MOE_TINY,
                            "algo.policy_average.decay=0.5", "epochs=2", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 0, result.stderr
    evaluated = torch.load(record / "evaluated2.pt")
    saved = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    for name, value in saved["policy"]["actor"].items():
        assert torch.equal(evaluated[f"module.1.{name}"], value)
    assert any(not torch.equal(evaluated[f"module.1.{name}"], value)
               for name, value in saved["learner"]["actor"].items())
