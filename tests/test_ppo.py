"""PPO's policy step (TorchRL's ClipPPOLoss in the on-policy learner): it improves the surrogate, its
KL is what it says, a KL target stops it, padding changes nothing, bad values are refused, and
``algo=ppo`` trains and resumes exactly."""

from __future__ import annotations

import math

import pytest
import torch
from test_token_policy import QUADRUPED, SNAKE, padded, robots, transformer, trpo_batch
from test_train import TINY, assert_same_training_state, run_train, straight_and_resumed
from test_trpo import _single_thread_and_seed, all_equal, collect, snapshot  # noqa: F401 (an autouse fixture)

from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import ClippedStep, ClippedSurrogate, TRPOLoss


def flat_case(**settings):
    actor, critic = make_actor(4, 2, (16, 16)), make_critic(4, (16, 16))
    loss = TRPOLoss(actor, critic)
    batch = collect(loss, torch.randn(8, 64, 4), done_every=16)
    loss.compute_advantage(batch)
    flat = batch.reshape(-1)
    step = ClippedStep(loss, actor, ClippedSurrogate(**settings), torch.Generator().manual_seed(0))
    return loss, flat, step


def test_a_clipped_step_improves_the_surrogate_and_reports_the_kl_it_took():
    loss, flat, step = flat_case(epochs=4, minibatch_size=64)
    before = loss(flat)
    assert before["kl"].abs() < 1e-6  # data collected by this very policy

    result = step(flat, loss.advantage(flat))

    after = loss(flat)  # the loss reads the actor the step moved
    assert result.accepted and result.skip_reason is None and result.policy_epochs == 4
    assert after["kl"].item() == pytest.approx(result.kl, rel=1e-4) and result.kl > 0
    assert (before["loss_objective"] - after["loss_objective"]).item() == pytest.approx(
        result.surrogate_improvement, rel=1e-3)
    assert result.surrogate_improvement > 0
    assert 0 <= result.clip_fraction <= 1
    assert set(result.as_metrics()) >= {"train/kl", "train/surrogate_improvement", "train/clip_fraction",
                                        "train/policy_epochs", "train/step_accepted"}


def test_a_kl_target_stops_the_step_at_the_first_minibatch_past_it():
    # 512 samples, minibatches of 64: 8 a pass. The first minibatch meets the policy that collected
    # the batch (KL 0) and steps; the second already finds it moved past the tiny target.
    loss, flat, step = flat_case(epochs=10, target_kl=1e-8)
    result = step(flat, loss.advantage(flat))
    assert result.accepted and result.policy_epochs == pytest.approx(1 / 8) and result.kl > 1.5e-8
    # Within a pass: a target the first pass passes stops the step before the set epochs.
    loss, flat, step = flat_case(epochs=10)
    free_kl = step(flat, loss.advantage(flat)).kl
    loss, flat, step = flat_case(epochs=10, target_kl=free_kl / 4)
    stopped = step(flat, loss.advantage(flat))
    assert 0 < stopped.policy_epochs < 10 and stopped.policy_epochs != int(stopped.policy_epochs)
    assert stopped.kl < free_kl
    loss, flat, step = flat_case(epochs=3, target_kl=10.0)
    assert step(flat, loss.advantage(flat)).policy_epochs == 3


def test_a_non_finite_advantage_or_step_leaves_the_actor_and_its_optimizer_as_they_were():
    loss, flat, step = flat_case()
    params, original = loss.actor_parameters(), snapshot(loss.actor_parameters())
    advantage = loss.advantage(flat)
    advantage[3] = math.nan
    result = step(flat, advantage)
    assert not result.accepted and "non-finite" in result.skip_reason and all_equal(params, original)
    # A step whose parameters blow up (an absurd learning rate) is rolled back, Adam's state too.
    loss, flat, step = flat_case(lr=1e30, max_grad_norm=1e30)
    params, original = loss.actor_parameters(), snapshot(loss.actor_parameters())
    result = step(flat, loss.advantage(flat))
    assert not result.accepted and "non-finite" in result.skip_reason
    assert all_equal(params, original) and step.optimizer.state_dict()["state"] == {}


def test_padding_leaves_the_clipped_step_unchanged():
    (actor, critic), (twin_actor, twin_critic) = transformer(dtype=torch.float64), transformer(dtype=torch.float64)
    twin_actor.load_state_dict(actor.state_dict())
    twin_critic.load_state_dict(critic.state_dict())
    loss, twin = TRPOLoss(actor, critic), TRPOLoss(twin_actor, twin_critic)
    batch = trpo_batch(loss, robots([SNAKE, QUADRUPED], length=7, batch=64, dtype=torch.float64))
    settings = ClippedSurrogate(epochs=2, minibatch_size=16)
    start = snapshot(loss.actor_parameters())

    result = ClippedStep(loss, actor, settings, torch.Generator().manual_seed(1))(batch, loss.advantage(batch))
    twin_result = ClippedStep(twin, twin_actor, settings, torch.Generator().manual_seed(1))(
        padded(batch, 11), twin.advantage(padded(batch, 11)))

    assert result.accepted and twin_result.accepted
    assert twin_result.kl == pytest.approx(result.kl, rel=1e-6)
    for param, twin_param in zip(loss.actor_parameters(), twin.actor_parameters(), strict=True):
        torch.testing.assert_close(twin_param, param, atol=1e-9, rtol=1e-7)
    assert not all_equal(loss.actor_parameters(), start)


@pytest.mark.parametrize(("setting", "value"), [("epochs", 0), ("minibatch_size", 2.5), ("lr", -1e-3),
                                                ("clip_epsilon", 0), ("max_grad_norm", math.inf),
                                                ("target_kl", 0.0), ("epochs", True)])
def test_bad_clipped_step_settings_raise_naming_the_value(setting, value):
    with pytest.raises(ValueError, match=f"{setting} must be .* got {value!r}"):
        ClippedSurrogate(**{setting: value})


@pytest.mark.slow
def test_a_ppo_run_trains_and_resumes_exactly_and_bad_settings_are_named(tmp_path):
    ppo = [*TINY, "algo=ppo", "algo.policy_epochs=2", "algo.policy_minibatch_size=8"]
    a, b, _ = straight_and_resumed(tmp_path, ppo, first=2, total=3)
    assert a["epoch"] == b["epoch"] == 3 and a["config"]["algo"]["name"] == "ppo"
    assert_same_training_state(a, b)
    assert a["learner"]["clipped_step"]["optimizer"]["state"]  # the actor's Adam state is saved ...
    for key, value in a["learner"]["clipped_step"]["optimizer"]["state"][0].items():
        torch.testing.assert_close(value, b["learner"]["clipped_step"]["optimizer"]["state"][0][key], rtol=0, atol=0)
    bad = run_train(*ppo, "algo.clip_epsilon=-0.2", f"hydra.run.dir={tmp_path / 'bad'}")
    assert bad.returncode != 0 and "clip_epsilon must be a positive finite number, got -0.2" in bad.stderr
