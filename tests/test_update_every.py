"""``algo.update_every``: an off-policy learner steps between chunks of the epoch as they are collected."""

from __future__ import annotations

import copy
import csv
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from test_off_policy import MBPO_TINY
from test_train import run_train, straight_and_resumed

from unipolicy_rl.factories import make_learner, make_real_collector
from unipolicy_rl.validation import validate_config

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["env=gym", "env.id=Pendulum-v1", "algo=sac", "env.frames_per_epoch=200", "epochs=1",
         "algo.actor_hidden=[32]", "algo.critic_hidden=[32]", "algo.batch_size=32"]


def composed(*overrides: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=[*SMALL, *overrides])


def one_epoch(cfg, hook=None):
    """The first real epoch of a fresh learner (the same initial weights every call), collected with
    ``hook`` (the learner's update_chunk, recorded) between chunks where ``algo.update_every`` is set."""
    torch.manual_seed(0)
    learner = make_learner(cfg, 3, 1)
    between = None
    if cfg.algo.update_every is not None:
        between = (lambda chunk: hook(learner, chunk)) if hook else learner.update_chunk
    with make_real_collector(cfg, learner.policy, full_state=False, between_chunks=between) as real:
        batch = next(iter(real))
    return learner, batch


def test_an_epoch_in_chunks_is_the_same_epoch_while_the_learner_does_not_step():
    """Before ``learning_starts`` nothing moves the policy, so collecting in chunks changes nothing:
    the same transitions, bit for bit, and the epoch's last step (only) truncated."""
    _, whole = one_epoch(composed("algo.learning_starts=100000"))
    learner, chunked = one_epoch(composed("algo.learning_starts=100000", "algo.update_every=40"))
    assert chunked.shape == whole.shape == torch.Size([1, 200])
    for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "truncated"),
                ("next", "done")):
        assert torch.equal(chunked[key], whole[key]), key
    truncated = chunked["next", "truncated"][0, :, 0]
    assert truncated[-1] and not truncated[:-1].any()  # Pendulum's 200 steps: the epoch's cut is the only end
    assert len(learner.buffer) == 200 and learner.gradient_steps == 0


def test_each_chunk_is_collected_by_the_policy_the_previous_chunk_s_steps_left():
    """With ``update_every=50`` the learner takes 50 steps (UTD 1) after each chunk of 50, and the
    next chunk's actions come from that policy: its Gaussian's mean on those observations is the
    updated policy's, not the one before the steps."""
    policies = []

    def record(learner, chunk):
        learner.update_chunk(chunk)
        policies.append(copy.deepcopy(learner.policy))

    cfg = composed("algo.learning_starts=0", "algo.update_every=50")
    torch.manual_seed(0)
    start = copy.deepcopy(make_learner(cfg, 3, 1).policy)
    learner, batch = one_epoch(cfg, record)
    assert len(policies) == 4 and learner.gradient_steps == 200
    with torch.no_grad():
        for index, before in enumerate([start, *policies[:-1]]):
            chunk = batch[0, 50 * index:50 * (index + 1)]
            collected = chunk["loc"]
            torch.testing.assert_close(before(chunk.select("observation").clone())["loc"], collected)
            if index:  # the policy did move: the one of a chunk earlier gives other means
                earlier = [start, *policies][index - 1]
                assert not torch.allclose(earlier(chunk.select("observation").clone())["loc"], collected)
    metrics = learner.update(batch)  # the epoch: only reported, its steps were taken
    assert learner.gradient_steps == 200 and len(learner.buffer) == 200
    assert metrics["train/gradient_steps"] == 200 and "train/loss_critic" in metrics


def test_update_every_of_the_whole_epoch_steps_once_after_it_as_one_chunk():
    learner, batch = one_epoch(composed("algo.learning_starts=0", "algo.update_every=200"))
    assert learner.gradient_steps == 200 and batch.shape == torch.Size([1, 200])
    assert learner.update(batch)["train/gradient_steps"] == 200


def test_the_learner_refuses_an_epoch_whose_chunks_it_did_not_see():
    torch.manual_seed(0)
    learner = make_learner(composed("algo.update_every=50"), 3, 1)
    _, batch = one_epoch(composed())  # collected in one piece
    with pytest.raises(ValueError, match="has seen 0 of this real batch's 200 transitions"):
        learner.update(batch)
    without = make_learner(composed(), 3, 1)
    with pytest.raises(ValueError, match="update_chunk needs algo.update_every"):
        without.update_chunk(batch)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["algo.update_every=0"], "algo.update_every must be an integer >= 1 .* got 0"),
        (["algo.update_every=30"], r"algo.update_every=30 must divide each env's steps per epoch "
                                   r"\(env.frames_per_epoch=200\)"),
        (["algo=trpo", "+algo.update_every=10"], "algo.update_every=10 steps an off-policy learner .* algo=trpo "
                                                  "learns from whole epochs"),
        (["env=walker", "algo=sac", "algo.update_every=10", "workers=2", "episodes_per_epoch=2"],
         "algo.update_every=10 steps the learner between chunks .* set workers=1 \\(got workers=2"),
    ],
)
def test_bad_update_every_is_refused_by_name(overrides, match):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        walker_or_trpo = "env=walker" in overrides or "algo=trpo" in overrides
        cfg = compose("config", overrides=overrides if walker_or_trpo else [*SMALL, *overrides])
    with pytest.raises(ValueError, match=match):
        validate_config(cfg)


def test_train_py_learns_between_chunks_and_counts_those_steps_as_updates(tmp_path):
    result = run_train(*SMALL[:-3], "epochs=2", "algo.update_every=50", "algo.learning_starts=100",
                       f"hydra.run.dir={tmp_path}", "progress_bar=false")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert [float(row["train/gradient_steps"]) for row in rows] == [150, 350]  # the first chunk's 50 earn none
    assert all(float(row["time/collect"]) >= 0 and float(row["time/update"]) > 0 for row in rows)


@pytest.mark.slow
def test_mbpo_learning_between_chunks_of_the_walkers_epoch_resumes_exactly(tmp_path):
    """On the walker (two robots, epochs of 10 steps in chunks of 5) and a world model: every step
    the real data earn is taken between chunks, and a resumed run continues as the straight one."""
    straight, resumed, _ = straight_and_resumed(tmp_path, [*MBPO_TINY, "algo.update_every=5"], first=2, total=3)
    assert straight["learner"]["gradient_steps"] == resumed["learner"]["gradient_steps"] == 2 * 3 * 20
    for key, value in straight["learner"]["loss"].items():
        assert torch.equal(value, resumed["learner"]["loss"][key]), f"{key} differs after resume"
