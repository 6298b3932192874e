"""The imagined reward lowered where the world model's members disagree (MOPO; ``imagination.disagreement_penalty``).

Its refusals (a weight that is not a positive number, a model whose members cannot disagree) are
tested beside the cut's, parametrized over both settings, in test_disagreement_cut.py."""

import math

import pytest
import torch
from tensordict import TensorDict
from test_disagreement_cut import GAP, LAYOUT, SPLIT, DivergingMembers, only_split_scale, origin_starts
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.collectors import HorizonSchedule, Imagination, ImaginationSettings, StoppingRule, imagined_metrics
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights
from unipolicy_rl.networks import make_actor
from unipolicy_rl.world_models import (
    DisagreementCut,
    DisagreementPenalty,
    ImaginedEnv,
    make_world_model,
)
from unipolicy_rl.world_models.disagreement import PenalizedReward

WEIGHT = 3.0


@pytest.fixture(scope="module")
def reference():
    env = BatchedWalkerEnv(1, full_state=True)
    env.close()  # only its specs are read
    return env


def rollout(reference, deterministic, penalty=None, cut=None, at=3, horizon=6):
    torch.manual_seed(0)
    world_model = make_world_model(DivergingMembers(at), RewardWeights(), deterministic=deterministic, cut=cut,
                                   penalty=penalty)
    env = ImaginedEnv(world_model, reference, origin_starts, batch_size=4)
    return env.rollout(horizon, make_actor(18, 4), break_when_any_done=False)


@pytest.mark.parametrize("deterministic", [False, True])  # True: one all-member prediction serves both
def test_each_step_loses_the_weight_times_its_members_disagreement_and_nothing_else_changes(reference,
                                                                                            deterministic):
    at = 3
    plain = rollout(reference, deterministic)
    penalized = rollout(reference, deterministic, DisagreementPenalty(WEIGHT, only_split_scale()))
    # The members part from x = 3 on (step 3 of a branch from the origin): GAP in the scale's units.
    expected = torch.zeros(4, 6, 1)
    expected[:, at:] = WEIGHT * GAP
    torch.testing.assert_close(penalized["next", "disagreement_penalty"], expected)
    torch.testing.assert_close(plain["next", "reward"] - penalized["next", "reward"], expected)
    for key in plain.keys(include_nested=True, leaves_only=True):  # no branch cut, same states and draws
        if key != ("next", "reward"):
            assert torch.equal(plain[key], penalized[key]), key
    assert not penalized["next", "done"].any()


def test_the_cut_and_the_penalty_read_one_measure(reference):
    scale = only_split_scale()
    both = rollout(reference, False, DisagreementPenalty(WEIGHT, scale), DisagreementCut(GAP / 2, scale))
    assert both["next", "disagreement_cut"][:, 3].all()  # the cut still ends the branch where they part
    torch.testing.assert_close(both["next", "disagreement_penalty"], WEIGHT * both["next", "disagreement"])
    with pytest.raises(ValueError, match="same scale"):
        make_world_model(DivergingMembers(3), RewardWeights(), cut=DisagreementCut(1.0, scale),
                         penalty=DisagreementPenalty(WEIGHT, 2 * scale))


def test_a_member_that_blew_up_costs_the_worst_finite_disagreement_of_the_batch():
    reward = torch.tensor([[1.0], [1.0], [1.0]])
    disagreement = torch.tensor([[0.2], [math.inf], [0.5]])
    penalized, penalty = PenalizedReward(2.0)(reward, disagreement)
    torch.testing.assert_close(penalty, torch.tensor([[0.4], [1.0], [1.0]]))
    torch.testing.assert_close(penalized, torch.tensor([[0.6], [0.0], [0.0]]))


@pytest.mark.parametrize("deterministic", [False, True])
def test_the_imagined_env_with_the_penalty_passes_torchrls_checks(reference, deterministic):
    world_model = make_world_model(DivergingMembers(1), RewardWeights(), deterministic=deterministic,
                                   penalty=DisagreementPenalty(WEIGHT, only_split_scale()))
    check_env_specs(ImaginedEnv(world_model, reference, origin_starts, batch_size=3))


def test_imagination_with_the_penalty_logs_what_it_took_in_the_buffers_units(reference):
    n = 50
    state = torch.zeros(n, LAYOUT.size)
    next_state = state.clone()
    next_state[:, SPLIT] = torch.linspace(-1.0, 1.0, n)  # the only output that changes in the data
    transitions = TensorDict({"state": state, "next_state": next_state, "action": torch.zeros(n, 4),
                              "design": torch.full((n, 2), 0.5)}, [n])
    scale = float(next_state[:, SPLIT].std(correction=0))
    settings = ImaginationSettings(steps_per_batch=24, horizon=HorizonSchedule(6, 6), disagreement_penalty=WEIGHT,
                                   stopping=StoppingRule(kind="fixed", max_updates=1))
    imagination = Imagination(DivergingMembers(at=3), reference, RewardWeights(), settings, seed=0, episode_length=10)
    batch = next(iter(imagination.epoch(1, transitions, make_actor(18, 4))))
    metrics = imagined_metrics(batch)
    # Three of each row's six steps (x = 3, 4, 5) have members that part by GAP / scale.
    assert math.isclose(metrics["imagined/disagreement"], GAP / scale / 2, rel_tol=1e-5)
    assert math.isclose(metrics["imagined/disagreement_penalty"], WEIGHT * GAP / scale / 2, rel_tol=1e-5)
    assert "imagined/cut_share" not in metrics and metrics["imagined/branch_length"] == 6.0
