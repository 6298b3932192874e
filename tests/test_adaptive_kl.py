"""imagination.adaptive_kl: the imagined updates' KL bound shrinks as the model's fresh error rises,
is logged per epoch, and bounds those updates only; off, nothing is touched."""

import csv
import math
from types import SimpleNamespace

import pytest
from test_policy_average import composed
from test_train import MOE_TINY, run_train

from unipolicy_rl.objectives import TrustRegion
from unipolicy_rl.objectives.adaptive_kl import IMAGINED_MAX_KL, AdaptiveKL, imagined_trust_region

RULE = AdaptiveKL(reference=0.1, floor=0.002)


@pytest.mark.parametrize(("fresh_error", "bound"), [
    (None, 0.01),          # no fresh error yet (the first epoch): the configured bound
    (0.05, 0.01),          # a model better than the reference: the configured bound
    (0.1, 0.01),
    (0.2, 0.005),          # twice as wrong: half the bound
    (0.4, 0.0025),
    (5.0, 0.002),          # far off: the floor
    (math.nan, 0.002),     # a model that predicts NaN: the floor
])
def test_the_bound_is_max_kl_scaled_by_reference_over_the_fresh_error_above_the_floor(fresh_error, bound):
    assert RULE.bound(0.01, fresh_error) == pytest.approx(bound)


def test_off_the_bound_is_max_kl_whatever_the_error():
    assert not AdaptiveKL().on and AdaptiveKL().bound(0.01, 5.0) == 0.01


@pytest.mark.parametrize(("settings", "match"), [
    ({"floor": 0.003}, "adaptive_kl.floor=0.003 without adaptive_kl.reference"),
    ({"reference": 0.1}, "adaptive_kl.floor must be a positive number"),
    ({"reference": -0.1, "floor": 0.003}, "adaptive_kl.reference must be a positive number"),
    ({"reference": 0.1, "floor": 0.0}, "adaptive_kl.floor must be a positive number"),
])
def test_bad_settings_are_refused_by_name(settings, match):
    with pytest.raises(ValueError, match=match):
        AdaptiveKL(**settings)


def test_the_bound_holds_within_the_block_only_and_off_touches_nothing():
    learner = SimpleNamespace(updater=SimpleNamespace(trust_region=TrustRegion(max_kl=0.01, damping=0.2)))
    with imagined_trust_region(RULE, learner, 0.4) as metrics:
        assert learner.updater.trust_region == TrustRegion(max_kl=0.0025, damping=0.2)
    assert metrics == {IMAGINED_MAX_KL: pytest.approx(0.0025)}
    assert learner.updater.trust_region == TrustRegion(max_kl=0.01, damping=0.2)
    with imagined_trust_region(AdaptiveKL(), object(), 0.4) as metrics:  # (an object with no updater at all)
        pass
    assert metrics == {}


@pytest.mark.parametrize(("overrides", "match"), [
    (["algo=ppo", "algo.critic_fit=inline"], "imagination.adaptive_kl shrinks TRPO's KL bound"),
    (["algo.max_kl=0.001"], "imagination.adaptive_kl.floor=0.002 exceeds algo.max_kl=0.001"),
])
def test_a_rule_without_a_trust_region_to_shrink_is_refused(overrides, match):
    from unipolicy_rl.validation import validate_config

    cfg = composed("source=moe", "imagination.adaptive_kl.reference=0.1", "imagination.adaptive_kl.floor=0.002",
                   *overrides)
    with pytest.raises(ValueError, match=match):
        validate_config(cfg)


@pytest.mark.slow
def test_a_run_logs_each_epoch_s_bound_and_its_imagined_steps_keep_within_it(tmp_path):
    # A reference far below any real error: from the second epoch on the bound shrinks.
    result = run_train(*MOE_TINY, "epochs=3", "imagination.stopping.kind=fixed",
                       "imagination.adaptive_kl.reference=1e-4", "imagination.adaptive_kl.floor=0.001",
                       f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    with (tmp_path / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    real = {row["epoch"]: row for row in rows if row["imagined"] == "0.0"}
    assert float(real["1"][IMAGINED_MAX_KL]) == 0.01  # no fresh error yet: algo.max_kl
    for epoch in ("2", "3"):
        bound = float(real[epoch][IMAGINED_MAX_KL])
        assert bound == pytest.approx(max(0.001, 0.01 * 1e-4 / float(real[epoch]["model/fresh_error"])))
        assert bound < 0.01
        kls = [float(row["train/kl"]) for row in rows if row["imagined"] == "1.0" and row["epoch"] == epoch]
        assert kls and max(kls) <= bound + 1e-9 and max(kls) > 0
