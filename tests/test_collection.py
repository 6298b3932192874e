"""Collection for training: observation statistics and the collector's worker processes."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

from unipolicy_rl.collectors import RealEpochCollector
from unipolicy_rl.factories import make_collector
from unipolicy_rl.observation_statistics import MIN_SCALE, ObservationStatistics, refresh_normalizer
from unipolicy_rl.policy import NORMALIZED_OBSERVATION, make_actor_critic, make_collecting_policy, make_observation_norm
from unipolicy_rl.validation import validate_config

CONF = Path(__file__).resolve().parents[1] / "conf"


def test_statistics_merged_over_batches_equal_those_of_all_the_data():
    data = torch.randn(1000, 5, dtype=torch.float64) * torch.tensor([1.0, 2.0, 0.5, 10.0, 3.0]) + 4.0
    statistics = ObservationStatistics(5)
    for chunk in (data[:7], data[7:300], data[300:].reshape(35, 20, 5)):  # uneven, and batched shapes
        statistics.update(chunk)
    assert statistics.count == 1000
    torch.testing.assert_close(statistics.mean, data.mean(0))
    torch.testing.assert_close(statistics.scale, data.std(0, correction=0).float())


def test_a_constant_coordinate_gets_the_floor_scale_not_zero():
    statistics = ObservationStatistics(2)
    assert torch.equal(statistics.scale, torch.ones(2))  # identity before any data
    statistics.update(torch.tensor([[1.0, 3.0], [2.0, 3.0]]))
    assert statistics.scale[1] == pytest.approx(MIN_SCALE)


@pytest.mark.parametrize("bad", [torch.zeros(4, 3), torch.tensor([[float("nan"), 0.0]])])
def test_bad_observations_are_refused(bad):
    with pytest.raises(ValueError):
        ObservationStatistics(2).update(bad)


def _outputs(policy, critic, normalizer, observations):
    with torch.no_grad():
        step = policy(TensorDict({"observation": observations.clone()}, batch_size=[len(observations)]))
        value = critic(normalizer(TensorDict({"observation": observations}, batch_size=[len(observations)])))[
            "state_value"]
    return step["loc"], step["scale"], value


@pytest.mark.parametrize("refreshes", [1, 3])
def test_a_preserving_refresh_leaves_policy_and_critic_unchanged_and_a_jump_does_not(refreshes):
    """Observations far from the identity's (offset, very different scales, one near-constant
    coordinate at the scale floor): moving the normaliser alone changes the policy a lot; the
    preserving refresh re-expresses the first layers so nothing the networks output changes."""
    cfg = tiny_config(workers=1)
    torch.manual_seed(0)
    spread = torch.tensor([0.1, 5.0, 1e-5, 2.0] * 4 + [1.0, 0.3])
    observations = [torch.randn(64, 18) * spread + torch.arange(18.0) for _ in range(refreshes + 1)]
    runs = {}
    for mode in ("preserve", "jump"):
        torch.manual_seed(1)
        actor, critic = make_actor_critic(cfg, 18, 4)
        normalizer = make_observation_norm(18)
        policy = make_collecting_policy(normalizer, actor)
        statistics = ObservationStatistics(18)
        changes = []
        for batch in observations[:refreshes]:
            before = _outputs(policy, critic, normalizer, observations[-1])
            statistics.update(batch)
            refresh_normalizer(statistics, normalizer, (actor, critic), mode)
            after = _outputs(policy, critic, normalizer, observations[-1])
            changes.append(max((a - b).abs().max().item() for a, b in zip(after, before, strict=True)))
        torch.testing.assert_close(normalizer.scale, statistics.scale)  # the normaliser moved in both modes
        runs[mode] = max(changes)
    assert runs["preserve"] < 1e-4
    assert runs["jump"] > 1e-2


def test_an_unknown_refresh_mode_is_refused_by_name():
    normalizer = make_observation_norm(2)
    with pytest.raises(ValueError, match="'rescale'"):
        refresh_normalizer(ObservationStatistics(2), normalizer, (), "rescale")


def tiny_config(workers: int, *overrides: str):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=[f"workers={workers}", f"episodes_per_epoch={2 * workers}",
                                            "robot.episode_length=5", *overrides])


@pytest.mark.slow
def test_worker_processes_normalise_with_the_statistics_the_trainer_sends():
    """The collecting policy runs in the workers: after new statistics and a weight update,
    the next batch must have been normalised with them, and hold one epoch of every robot."""
    cfg = tiny_config(workers=2)
    actor, _ = make_actor_critic(cfg, 18, 4)
    normalizer = make_observation_norm(18)
    collector = make_collector(cfg, make_collecting_policy(normalizer, actor), epochs=2)
    try:
        batches = iter(collector)
        first = next(batches)
        assert first.shape == (2, 2, 5)  # workers x robots each x steps
        # One episode per robot: truncated (not terminated) at the last step only, with the
        # episode's whole reward summed there.
        done, truncated = first["next", "done"].squeeze(-1), first["next", "truncated"].squeeze(-1)
        assert done[..., -1].all() and not done[..., :-1].any() and torch.equal(done, truncated)
        assert not first["next", "terminated"].any()
        torch.testing.assert_close(first["next", "episode_reward"][..., -1, 0], first["next", "reward"].sum((-2, -1)))
        torch.testing.assert_close(first[NORMALIZED_OBSERVATION], first["observation"])  # identity so far
        statistics = ObservationStatistics(18)
        statistics.update(first["observation"])
        statistics.copy_to(normalizer)
        collector.update_policy_weights_()
        second = next(batches)
        expected = (second["observation"] - statistics.loc) / statistics.scale
        torch.testing.assert_close(second[NORMALIZED_OBSERVATION], expected)
    finally:
        collector.shutdown()


@pytest.mark.slow
def test_ray_workers_collect_reseeded_epochs_with_the_statistics_the_trainer_sends():
    """collector.backend=ray: two Ray actors on a local cluster step the robots. A batch is one
    epoch of every robot, shaped as the worker processes' are; reseeding repeats an epoch exactly
    (robots and action noise); new statistics reach the actors with the weights; and shutting
    the collector down stops the cluster it started."""
    ray = pytest.importorskip("ray")
    cfg = tiny_config(2, "collector.backend=ray")
    actor, _ = make_actor_critic(cfg, 18, 4)
    normalizer = make_observation_norm(18)
    collector = RealEpochCollector(make_collector(cfg, make_collecting_policy(normalizer, actor), epochs=3),
                                   seed=7, epochs=3, frames_per_batch=20)
    try:
        batches = iter(collector.collector)
        collector._restart_randomness(0)
        first = next(batches)
        assert first.shape == (2, 2, 5)  # workers x robots each x steps
        done = first["next", "done"].squeeze(-1)
        assert done[..., -1].all() and not done[..., :-1].any()
        collector._restart_randomness(0)
        again = next(batches)
        for key in ("observation", "action", ("next", "observation"), "design"):
            torch.testing.assert_close(again[key], first[key], rtol=0, atol=0)
        assert not torch.equal(first["action"][0], first["action"][1])  # the workers draw different noise
        statistics = ObservationStatistics(18)
        statistics.update(first["observation"])
        statistics.copy_to(normalizer)
        collector.update_policy_weights_()
        collector._restart_randomness(1)
        second = next(batches)
        expected = (second["observation"] - statistics.loc) / statistics.scale
        torch.testing.assert_close(second[NORMALIZED_OBSERVATION], expected)
    finally:
        collector.shutdown()
    assert not ray.is_initialized()


def test_an_unknown_collector_backend_is_refused_by_name():
    cfg = tiny_config(1, "collector.backend=slurm")
    with pytest.raises(ValueError, match="collector.backend.*slurm"):
        validate_config(cfg)
