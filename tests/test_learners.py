"""The Learner interface: TRPO implements it, and the training loop takes an off-policy learner
(its own replay buffer, many gradient steps per real step) without a special case."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fingerprint import RELATIVE_TOLERANCE, fingerprint
from tensordict import TensorDict

from unipolicy_rl.checkpoint import load_checkpoint, load_policy
from unipolicy_rl.learners import Learner, TRPOLearner

ROOT = Path(__file__).resolve().parents[1]
TINY = ["episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false", "workers=1"]
# train.py with the TRPO learner replaced by the off-policy test double (tests/replay_learner.py).
WITH_REPLAY_LEARNER = f"""
import sys
sys.path.insert(0, {str(ROOT / "tests")!r})
from replay_learner import ReplayLearner
import unipolicy_rl.factories as factories
factories.LEARNERS["trpo"] = ReplayLearner
"""


def run_train_with(patch: str, *overrides: str) -> subprocess.CompletedProcess:
    script = "\n".join(["import runpy, sys", patch, f"sys.argv = ['train.py', *{list(overrides)!r}]",
                        f"runpy.run_path({str(ROOT / 'train.py')!r}, run_name='__main__')"])
    return subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          check=False)


def _rows(run_dir: Path) -> list[dict]:
    with (run_dir / "metrics.csv").open() as file:
        return list(csv.DictReader(file))


@pytest.mark.slow
@pytest.mark.parametrize("source", ["se", "moe"])
def test_the_loop_trains_an_off_policy_learner_that_keeps_its_own_buffer(tmp_path, source):
    model_based = ["source=moe", "imagination.steps_per_batch=20", "imagination.horizon.start=2",
                   "imagination.horizon.end=2", "world_model.model.hidden=[8]", "world_model.trainer.max_epochs=1",
                   "imagination.stopping.kind=fixed", "imagination.stopping.max_updates=2",
                   "imagination.train_on_real=true", "algo.critic_fit=inline"] if source == "moe" else []
    result = run_train_with(WITH_REPLAY_LEARNER, *TINY, *model_based, "epochs=3", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    rows = _rows(tmp_path)
    real = [row for row in rows if row["imagined"] == "0.0"]
    # Every real step reaches the learner's own buffer (and, model-based, 2 updates of 20 imagined steps an
    # epoch), and it takes 2 gradient steps per transition it is given.
    # (A real row logs the update on the real batch, which comes before the epoch's imagined ones.)
    per_epoch = 20 + (2 * 20 if source == "moe" else 0)
    assert [float(row["train/buffer_size"]) for row in real] == [20 + per_epoch * k for k in (0, 1, 2)]
    last = max(rows, key=lambda row: float(row["train/gradient_steps"]))
    assert float(last["train/buffer_size"]) == 3 * per_epoch
    assert float(last["train/gradient_steps"]) == 2 * 3 * per_epoch
    assert load_policy(tmp_path / "checkpoint.pt").act(torch.zeros(18).numpy()).shape == (4,)


@pytest.mark.slow
def test_an_off_policy_learner_resumes_with_its_buffer_exactly(tmp_path):
    straight = run_train_with(WITH_REPLAY_LEARNER, *TINY, "epochs=3", f"hydra.run.dir={tmp_path / 'straight'}")
    first = run_train_with(WITH_REPLAY_LEARNER, *TINY, "epochs=2", f"hydra.run.dir={tmp_path / 'first'}")
    resumed = run_train_with(WITH_REPLAY_LEARNER, *TINY, "epochs=3", f"resume={tmp_path / 'first' / 'checkpoint.pt'}",
                             f"hydra.run.dir={tmp_path / 'resumed'}")
    for result in (straight, first, resumed):
        assert result.returncode == 0, result.stderr
    a = load_checkpoint(tmp_path / "straight" / "checkpoint.pt")["learner"]
    b = load_checkpoint(tmp_path / "resumed" / "checkpoint.pt")["learner"]
    assert a["gradient_steps"] == b["gradient_steps"] == 120
    for key, value in a["actor"].items():
        assert torch.equal(value, b["actor"][key]), f"actor {key} differs after resume"


def _trpo_learner():
    from hydra import compose, initialize_config_dir

    from unipolicy_rl.factories import make_learner

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config")
    torch.manual_seed(0)
    return make_learner(cfg, 18, 4)


def test_trpo_is_a_learner_and_names_what_it_reads_from_a_batch():
    learner = _trpo_learner()
    assert isinstance(learner, TRPOLearner) and isinstance(learner, Learner)
    assert {"observation", "action", "action_log_prob", "loc", "scale", ("next", "reward"),
            ("next", "done"), ("next", "terminated"), ("next", "observation")} == set(learner.batch_keys)


def test_the_normaliser_refresh_reports_the_kl_it_causes_with_the_losses_kl():
    """``jump`` only moves the normaliser: the policy changes by the Gaussian KL written out by hand;
    ``preserve`` re-expresses the first layers: it does not change at all."""
    spread = torch.tensor([0.1, 5.0, 1e-5, 2.0] * 4 + [1.0, 0.3])
    observations = torch.randn(2, 64, 18, generator=torch.Generator().manual_seed(0)) * spread + torch.arange(18.0)
    kls = {}
    for mode in ("preserve", "jump"):
        learner = _trpo_learner()
        learner.normalizer_refresh = mode
        probe = TensorDict({"observation": observations.reshape(-1, 18)}, batch_size=[128])
        with torch.no_grad():
            before = learner.policy(probe.clone())
            batch = TensorDict({"observation": observations}, batch_size=[2, 64])
            kls[mode] = learner.refresh_observation_normalizer(batch)["train/refresh_kl"]
            after = learner.policy(probe.clone())
        (m1, s1), (m2, s2) = (before["loc"], before["scale"]), (after["loc"], after["scale"])
        by_hand = (torch.log(s2 / s1) + (s1**2 + (m1 - m2) ** 2) / (2 * s2**2) - 0.5).sum(-1).mean()
        assert kls[mode] == pytest.approx(float(by_hand), abs=1e-6)
    assert abs(kls["preserve"]) < 1e-6 < kls["jump"]


# Recorded on main (torch 2.13 CPU, one thread, AVX-512): two TRPO updates and normaliser refreshes
# of the default learner, as the fingerprints (tests/fingerprint.py) of the actor's, the critic's
# and the observation statistics' numbers, then the last update's KL.
DEFAULT_LEARNER_FINGERPRINT = [1128.554569445152, 506.720950693019, 1134.4549242612484, 506.5710167524876,
                               43599.21416491103, 106542211.31360155, 0.007744933478534222]


def test_the_default_learner_s_numbers_have_not_moved():
    """The flat path (robot=vertebrate policy=mlp, the default) computes what it did."""
    from hydra import compose, initialize_config_dir

    from unipolicy_rl.factories import make_learner

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["algo.critic_epochs=2"])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        learner = make_learner(cfg, 18, 4)
        generator = torch.Generator().manual_seed(1)
        for _ in range(2):
            batch = _collected_batch(learner, generator)
            metrics = learner.update(batch)
            learner.refresh_observation_normalizer(batch)
    finally:
        torch.set_num_threads(threads)
    state = learner.state_dict()
    statistics = state["observation_statistics"]
    numbers = [*fingerprint(list(state["actor"].values())), *fingerprint(list(state["critic"].values())),
               *fingerprint([statistics["mean"], statistics["squared_deviations"]]), float(metrics["train/kl"])]
    if not torch.__version__.startswith("2.13"):
        pytest.skip(f"the recorded numbers are torch 2.13's; this is {torch.__version__}")
    assert numbers == pytest.approx(DEFAULT_LEARNER_FINGERPRINT, rel=RELATIVE_TOLERANCE)


def _collected_batch(learner, generator: torch.Generator) -> TensorDict:
    """A batch as a real epoch gives it: two 64-step rows the learner's own policy acted in
    (observations and rewards drawn from ``generator``)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    batch = TensorDict({"observation": torch.randn(2, 64, 18, generator=generator) * 3 + 1}, [2, 64])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = learner.policy(batch)
    done = torch.zeros(2, 64, 1, dtype=torch.bool)
    done[:, 31::32] = True
    batch["next"] = TensorDict({"observation": torch.randn(2, 64, 18, generator=generator) * 3 + 1,
                                "reward": torch.randn(2, 64, 1, generator=generator), "done": done,
                                "terminated": torch.zeros_like(done)}, [2, 64])
    return batch


def test_the_real_surrogate_is_trpo_s_own_on_the_batch_it_updated_on():
    """Zero at the collecting policy (standardised advantages), the step's own surrogate improvement
    after the update, unchanged by a preserving refresh of the normaliser (it re-normalises the raw
    observations), and refused on a batch no update has given advantages."""
    learner = _trpo_learner()
    batch = _collected_batch(learner, torch.Generator().manual_seed(1))
    with pytest.raises(KeyError, match="'advantage' from a TRPO update"):
        learner.real_surrogate(batch)
    learner.normalizer(batch["next"])
    learner.loss.compute_advantage(batch)
    terms = learner.real_surrogate(batch)
    assert terms.shape == (batch.numel(),)  # one term per sample, for RealCheck to pair
    assert abs(float(terms.mean())) < 1e-6
    metrics = learner.update(batch)
    assert metrics["train/step_accepted"] == 1.0
    after_step = float(learner.real_surrogate(batch).mean())
    assert after_step == pytest.approx(metrics["train/surrogate_improvement"], rel=1e-4)
    assert after_step > 0
    # preserve: the default refresh
    learner.refresh_observation_normalizer(_collected_batch(learner, torch.Generator().manual_seed(2)))
    assert float(learner.real_surrogate(batch).mean()) == pytest.approx(after_step, rel=1e-4)


@pytest.mark.slow  # (a train.py process of about 8 s)
def test_a_registered_learner_that_lacks_part_of_the_interface_is_refused_by_name_before_training(tmp_path):
    """A user's learner without ``close`` (say, written before it joined the interface) stops the run at
    start-up with the missing names, not after its last epoch."""
    patch = WITH_REPLAY_LEARNER + "del ReplayLearner.close\n"
    result = run_train_with(patch, *TINY, "epochs=3", f"hydra.run.dir={tmp_path}")
    assert result.returncode != 0
    assert ("the learner of algo.name='trpo' (ReplayLearner) lacks close of the Learner interface"
            in result.stderr), result.stderr[-2000:]
    assert not (tmp_path / "metrics.csv").exists()  # nothing trained
