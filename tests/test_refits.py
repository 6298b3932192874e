"""``imagination.refit_every``: MBPO's model refits, and their branches, while the epoch is collected."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from test_off_policy import MBPO_TINY
from test_train import run_train, straight_and_resumed

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.collectors import COLLECTED_IN, ImaginationSettings
from unipolicy_rl.factories import (
    make_learner,
    make_real_collector,
    make_refits_within_epoch,
    make_world_model_parts,
)
from unipolicy_rl.validation import validate_config

ROOT = Path(__file__).resolve().parents[1]
# Pendulum, epochs of 200 steps, learning in chunks of 50, a refit every 100 (one within each epoch)
SMALL = ["env=gym", "env.id=Pendulum-v1", "source=moe", "algo=sac", "env.frames_per_epoch=200",
         "algo.actor_hidden=[32]", "algo.critic_hidden=[32]", "algo.batch_size=32", "algo.learning_starts=0",
         "algo.update_every=50", "imagination.refit_every=100", "imagination.steps_per_batch=300",
         "world_model.model.members=3", "world_model.model.elites=2", "world_model.model.hidden=[16]",
         "world_model.trainer.max_epochs=3", "world_model.trainer.num_threads=null"]


def composed(*overrides: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=[*SMALL, *overrides])


def test_a_refit_within_the_epoch_fits_on_the_steps_so_far_and_hands_the_learner_their_branches():
    cfg = composed("epochs=1")
    validate_config(cfg)
    torch.manual_seed(0)
    learner = make_learner(cfg, 3, 1)
    world = make_world_model_parts(cfg, 1)
    untrained = {key: value.clone() for key, value in world.model.state_dict().items()}
    refits = make_refits_within_epoch(cfg, learner, world, learner.policy, epoch=1)
    with make_real_collector(cfg, learner.policy, full_state=True, between_chunks=refits) as real:
        batch = next(iter(real))
    # One refit, at step 100: the model's buffer holds the first 100 steps, the model was fitted
    # on them, and the learner's model buffer holds that fit's branches (300 one-step branches,
    # MBPO's first horizon), each from a state of those 100 steps.
    assert len(world.buffer) == 100
    assert any(not torch.equal(value, untrained[key]) for key, value in world.model.state_dict().items())
    assert len(learner.model_buffer) == 300
    starts = learner.model_buffer[:300]["observation"]
    nearest = torch.cdist(starts, batch[0]["observation"]).min(dim=1)  # among all 200 steps of the epoch
    assert nearest.values.max() < 5e-3  # (the model's state in float precision)
    assert nearest.indices.max() < 100  # none from after the refit
    # The loop's fit after the epoch takes the rest of it.
    rest = refits.rest_of_epoch(batch)
    assert rest.shape == torch.Size([1, 100])
    assert torch.equal(rest["observation"], batch[0:1, 100:]["observation"])
    assert refits.metrics()["model/refits_within_epoch"] == 1 and refits.epoch == 2
    with pytest.raises(ValueError, match="its chunks brought 0"):
        refits.rest_of_epoch(batch)  # the next epoch's chunks have not come


PENDULUM = ["env=gym", "env.id=Pendulum-v1", "env.frames_per_epoch=200"]


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ([*PENDULUM, "algo=sac", "algo.update_every=50", "imagination.refit_every=100"],
         "imagination.refit_every=100 refits a world model .* source=se has none"),
        ([*PENDULUM, "source=moe", "imagination.refit_every=100"],
         "imagination.refit_every=100 fills an off-policy learner's model buffer .* algo=trpo imagines after each "
         "epoch"),
        ([*PENDULUM, "source=moe", "algo=sac", "imagination.refit_every=100"],
         "imagination.refit_every=100 needs the learner to learn while the epoch is collected: set "
         "algo.update_every"),
        ([*PENDULUM, "source=moe", "algo=sac", "algo.update_every=20", "imagination.refit_every=50"],
         "imagination.refit_every=50 must be a multiple of algo.update_every=20"),
        ([*PENDULUM, "source=moe", "algo=sac", "algo.update_every=20", "imagination.refit_every=80"],
         r"imagination.refit_every=80 must divide each env's steps per epoch \(env.frames_per_epoch=200\)"),
        ([*SMALL, "imagination.fit_every=2"], "imagination.fit_every=2 skips the fits after some"),
        ([*SMALL, "imagination.background_fit=true"], "set imagination.background_fit=false"),
        ([*PENDULUM, "source=moe", "algo=sac", "algo.update_every=50", "imagination.refit_every=0"],
         r"imagination.refit_every must be a positive integer \(env steps between refits\) or null, got 0"),
    ],
)
def test_bad_refit_every_is_refused_by_name(overrides, match):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    with pytest.raises(ValueError, match=match):
        validate_config(cfg)


def test_refit_every_is_a_positive_integer_or_none():
    with pytest.raises(ValueError, match="refit_every must be a positive integer or None, got True"):
        ImaginationSettings(refit_every=True)
    assert ImaginationSettings(refit_every=250).refit_every == 250


def test_train_py_refits_within_each_epoch(tmp_path):
    result = run_train(*SMALL, "epochs=2", f"hydra.run.dir={tmp_path}", "progress_bar=false")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [row for row in csv.DictReader(open(tmp_path / "metrics.csv")) if row["imagined"] == "0.0"]
    assert [float(row["model/refits_within_epoch"]) for row in rows] == [1, 1]
    assert all(float(row["model/refit_seconds"]) > 0 for row in rows)
    # The model's buffer holds every real step once: each epoch's first 100 from its refit, the
    # other 100 from the fit after it.
    storage = load_checkpoint(tmp_path / "checkpoint.pt")["replay_buffer"]["_storage"]
    assert storage["_len"] == 400
    collected_in = storage["_storage"][COLLECTED_IN][:400]
    assert (collected_in == 1).sum() == 200 and (collected_in == 2).sum() == 200


@pytest.mark.slow
def test_refits_within_the_walkers_epoch_resume_exactly(tmp_path):
    """The walker (epochs of 10 steps, chunks of 5, a refit after the first 5): a resumed run
    continues as the straight one, the world model and the learner alike."""
    overrides = [*MBPO_TINY, "algo.update_every=5", "imagination.refit_every=5"]
    straight, resumed, _ = straight_and_resumed(tmp_path, overrides, first=2, total=3)
    for key, value in straight["learner"]["loss"].items():
        assert torch.equal(value, resumed["learner"]["loss"][key]), f"{key} differs after resume"
    for key, value in straight["world_model"].items():
        assert torch.equal(value, resumed["world_model"][key]), f"world model {key} differs after resume"
