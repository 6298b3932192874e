"""When the critic is fitted (``algo.critic_fit``): inline, one update late, or one update late on a
forked process. The process learns exactly what the lagged fit does, the lag is a real change
(flushed after every update it is the inline fit again), and a run with the fit on a process
resumes exactly."""

from __future__ import annotations

import pytest
import torch
from test_train import MOE_TINY, assert_same_training_state, load_checkpoint, run_train, straight_and_resumed
from test_trpo import _single_thread_and_seed, all_equal, collect, snapshot  # noqa: F401 (an autouse fixture)

from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater


def updater(critic_fit: str, seed: int = 0) -> TRPOUpdater:
    torch.manual_seed(seed)
    actor, critic = make_actor(4, 2, (16, 16)), make_critic(4, (16, 16))
    loss = TRPOLoss(actor, critic)
    return TRPOUpdater(loss, critic_epochs=2, critic_minibatch_size=32,
                       generator=torch.Generator().manual_seed(seed), critic_fit=critic_fit)


def batches(count: int) -> list:
    generator = torch.Generator().manual_seed(1)
    return [torch.randn(4, 32, 4, generator=generator) for _ in range(count)]


def train(one: TRPOUpdater, observations: list, flush_each: bool = False) -> list[torch.Tensor]:
    try:
        for obs in observations:
            torch.manual_seed(2)  # the same actions from the same policy
            one.update(collect(one.loss_module, obs, done_every=16))
            if flush_each:
                one.finish_critic_fit()
        one.finish_critic_fit()
        return snapshot([*one.loss_module.actor_parameters(), *one.loss_module.critic_parameters()])
    finally:
        one.close()


def test_the_fit_on_a_process_learns_exactly_what_the_lagged_fit_does_and_the_lag_is_real():
    data = batches(4)
    lagged = train(updater("lagged"), data)
    on_a_process = train(updater("process"), data)
    inline = train(updater("inline"), data)
    assert all_equal(on_a_process, lagged)
    assert not all_equal(lagged, inline)  # each update's advantages came from an older critic
    # Applied after every update, the pending fit is the inline fit again.
    assert all_equal(train(updater("lagged"), data, flush_each=True), inline)


def test_the_fit_process_leaves_ctrl_c_and_sigterm_to_the_training_process():
    """Both reach the whole process group; the child fits on, and close() still ends it."""
    import os
    import signal

    one = updater("process")
    data = batches(2)
    one.update(collect(one.loss_module, data[0], done_every=16))
    child = one.critic_process._process
    for number in (signal.SIGINT, signal.SIGTERM):
        os.kill(child.pid, number)
    one.update(collect(one.loss_module, data[1], done_every=16))  # the first fit arrives, the second starts
    assert one.finish_critic_fit().fitted and child.is_alive()
    one.close()
    assert not child.is_alive()


def test_a_pending_fit_is_applied_before_its_optimizer_state_is_read_and_bad_modes_are_named():
    one = updater("process")
    try:
        one.update(collect(one.loss_module, batches(1)[0], done_every=16))
        assert one.critic_process.pending
        with pytest.raises(RuntimeError, match="still pending"):
            one.critic_process.optimizer_state()
        assert one.finish_critic_fit().fitted and not one.critic_process.pending
        state, generator_state = one.critic_optimizer_state()
        assert state["state"] and generator_state is not None  # the child's Adam state, after its fit
        twin = updater("inline")
        twin.load_critic_optimizer_state(state, generator_state)
        assert torch.equal(twin.generator.get_state(), generator_state)
    finally:
        one.close()
    with pytest.raises(ValueError, match="critic_fit must be one of .* got 'later'"):
        updater("later")


def test_a_pending_fit_skipped_outside_an_update_counts_as_a_skipped_update():
    one = updater("lagged")
    one.update(collect(one.loss_module, batches(1)[0], done_every=16))
    assert one.consecutive_skips == 0
    before = snapshot(list(one.loss_module.critic_parameters()))
    one._lagged_batch[one.loss_module.tensor_keys.value_target][0] = float("nan")  # a diverged batch's targets
    result = one.finish_critic_fit()  # as a normaliser refresh or a checkpoint applies it
    assert not result.fitted and one.consecutive_skips == 1
    assert one.skip_reasons == ["critic fit: non-finite value target"]
    assert all_equal(snapshot(list(one.loss_module.critic_parameters())), before)
    assert one.finish_critic_fit() is None and one.consecutive_skips == 1  # nothing pending, nothing counted
    one.update(collect(one.loss_module, batches(2)[1], done_every=16))  # a good update ends the run of skips
    assert one.consecutive_skips == 0


@pytest.mark.slow
def test_a_model_based_run_with_its_critic_fit_on_a_process_resumes_exactly(tmp_path):
    a, b, _ = straight_and_resumed(tmp_path, [*MOE_TINY, "algo.critic_fit=process"], first=1, total=3)
    assert a["epoch"] == b["epoch"] == 3 and a["config"]["algo"]["critic_fit"] == "process"
    assert_same_training_state(a, b, world_model=True)
    lagged = run_train(*MOE_TINY, "algo.critic_fit=lagged", "epochs=3", f"hydra.run.dir={tmp_path / 'lagged'}")
    assert lagged.returncode == 0, lagged.stderr
    assert_same_training_state(a, load_checkpoint(tmp_path / "lagged" / "checkpoint.pt"), world_model=True)
    bad = run_train(*MOE_TINY, "algo.critic_fit=lagged", "imagination.train_on_real=true",
                    f"hydra.run.dir={tmp_path / 'bad'}")
    assert bad.returncode != 0 and "algo.critic_fit=lagged with imagination.train_on_real=true" in bad.stderr
    bad = run_train(*MOE_TINY, "algo=ppo", "algo.critic_fit=process", f"hydra.run.dir={tmp_path / 'bad_ppo'}")
    assert bad.returncode != 0 and "algo.critic_fit=process with algo=ppo" in bad.stderr


def composed(*overrides: str):
    from hydra import compose, initialize_config_dir
    from test_config_defaults import CONF

    with initialize_config_dir(str(CONF), version_base=None):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize(("overrides", "critic_fit", "fit_threads"), [
    ((), "inline", None),                                    # SE: no model, no spare time to overlap
    (("source=moe",), "process", 2),                         # the league's measure (docs/results.md)
    (("source=moe", "algo=ppo"), "inline", 2),               # PPO's shuffles share the fit's generator
    (("source=moe", "algo.critic_fit=lagged"), "lagged", 2),  # a setting of the user's wins
    (("source=pce",), "inline", None),                       # unmeasured there
])
def test_the_source_chooses_when_the_critic_is_fitted(overrides, critic_fit, fit_threads):
    from unipolicy_rl.validation import validate_config

    cfg = composed(*overrides)
    validate_config(cfg)
    assert cfg.algo.critic_fit == critic_fit
    if cfg.source.kind == "model":
        assert cfg.world_model.trainer.get("num_threads") == fit_threads


def test_a_real_batch_update_on_the_default_model_source_names_the_default_and_the_fix():
    from unipolicy_rl.validation import validate_config

    with pytest.raises(ValueError, match=r"algo.critic_fit=process \(source=moe's default\) with "
                                         r"imagination.train_on_real=true.*add algo.critic_fit=inline"):
        validate_config(composed("source=moe", "imagination.train_on_real=true"))
    validate_config(composed("source=moe", "imagination.train_on_real=true", "algo.critic_fit=inline"))


def test_closing_the_learner_ends_its_critic_process_and_twice_is_harmless():
    """train.py closes its learner when the run ends (or fails): the fit's process goes with it."""
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from unipolicy_rl.factories import make_learner

    learner = make_learner(composed("source=moe", "algo.actor_hidden=[16]", "algo.critic_hidden=[16]"), 4, 2)
    generator = torch.Generator().manual_seed(0)
    batch = TensorDict(observation=torch.randn(2, 32, 4, generator=generator), batch_size=[2, 32])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        learner.policy(batch)
    done = torch.zeros(2, 32, 1, dtype=torch.bool)
    done[:, -1] = True
    batch["next"] = TensorDict(observation=torch.randn(2, 32, 4, generator=generator),
                               reward=torch.randn(2, 32, 1, generator=generator), done=done,
                               terminated=torch.zeros_like(done), batch_size=[2, 32])
    learner.update(batch)
    child = learner.updater.critic_process._process
    assert child is not None and child.is_alive()  # the first fit runs beside the loop
    learner.close()
    assert not child.is_alive()
    learner.close()
