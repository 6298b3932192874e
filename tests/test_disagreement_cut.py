"""Imagined branches cut where the world model's members disagree (MACURA; ``imagination.disagreement_cut``)."""

import math

import pytest
import torch
from tensordict import TensorDict
from test_world_models import real_transitions
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.collectors import HorizonSchedule, Imagination, ImaginationSettings, StoppingRule, imagined_metrics
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights, RobotSettings
from unipolicy_rl.networks import make_actor
from unipolicy_rl.world_models import (
    CellEnsemble,
    ClosedFormTrainer,
    DisagreementCut,
    Dynamics,
    GaussianEnsemble,
    ImaginedEnv,
    ModelTrainer,
    PCEDynamics,
    StateLayout,
    make_world_model,
)
from unipolicy_rl.world_models.disagreement import MemberDisagreement, change_scale, member_predictions
from unipolicy_rl.world_models.imagined import PredictAndMeasureDisagreement

LAYOUT = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
X, SPLIT = 0, 4  # the base's x counts the steps; column 4 is where the members part
GAP = 0.5


class DivergingMembers:
    """A tiny :class:`Dynamics`: every step moves the base's x by 1 (a branch started at x = 0 is
    at x = t at step t); from x = ``at`` on, member k also moves column 4 by ``(k - 1) * GAP``, so
    the members' sample standard deviation there is exactly ``GAP`` and 0 before."""

    layout = LAYOUT

    def __init__(self, at: int, members: int = 3) -> None:
        self.at, self.members = at, members

    @property
    def device(self):
        return torch.device("cpu")

    @property
    def voting_members(self):
        return torch.arange(self.members)

    def draw_members(self, design, generator=None):
        return torch.zeros(design.shape[:-1], dtype=torch.long)

    def predict(self, state, action, design, member, deterministic=False):
        out = state.clone()
        out[..., X] += 1.0
        parted = (state[..., X] >= self.at - 0.5).to(state.dtype)
        out[..., SPLIT] += (member.reshape(state.shape[:-1]).to(state.dtype) - 1.0) * GAP * parted
        return out

    def memory_of(self, batch):
        return None


def only_split_scale() -> torch.Tensor:
    scale = torch.zeros(LAYOUT.robot_size)
    scale[SPLIT] = 1.0
    return scale


def origin_starts(n: int) -> TensorDict:
    return TensorDict({"state": torch.zeros(n, LAYOUT.size), "design": torch.tensor([[0.175, 0.5]]).expand(n, 2)},
                      [n])


@pytest.fixture(scope="module")
def reference():
    env = BatchedWalkerEnv(1, full_state=True)
    env.close()  # only its specs are read
    return env


def test_the_tiny_model_is_a_dynamics_and_its_disagreement_is_the_gap_from_the_known_step():
    model = DivergingMembers(at=3)
    assert isinstance(model, Dynamics)
    disagreement = MemberDisagreement(model, only_split_scale())
    state = torch.zeros(5, LAYOUT.size)
    state[:, X] = torch.arange(5.0)
    measured = disagreement(state, torch.zeros(5, 4), torch.full((5, 2), 0.5)).squeeze(-1)
    torch.testing.assert_close(measured, torch.tensor([0.0, 0.0, 0.0, GAP, GAP]))


@pytest.mark.parametrize("deterministic", [False, True])  # True: one all-member prediction serves both
def test_a_branch_is_cut_truncated_at_exactly_the_step_its_members_disagree_past_the_threshold(reference,
                                                                                              deterministic):
    at, horizon = 3, 6
    cut = DisagreementCut(GAP / 2, only_split_scale())
    world_model = make_world_model(DivergingMembers(at), RewardWeights(), deterministic=deterministic, cut=cut)
    env = ImaginedEnv(world_model, reference, origin_starts, batch_size=4)
    rollout = env.rollout(horizon, make_actor(18, 4), break_when_any_done=False)
    cut = rollout["next", "disagreement_cut"].squeeze(-1)
    expected = torch.zeros(4, horizon, dtype=torch.bool)
    expected[:, at] = True
    assert torch.equal(cut, expected)
    assert torch.equal(rollout["next", "truncated"].squeeze(-1), expected)
    assert torch.equal(rollout["next", "done"].squeeze(-1), expected)
    assert not rollout["next", "terminated"].any()  # the critic bootstraps at the cut
    torch.testing.assert_close(rollout["next", "disagreement"][:, at].squeeze(-1), torch.full((4,), GAP))
    # The cut step keeps its prediction; the row then restarts from a fresh real start (x = 0).
    assert (rollout["next", "state"][:, at, X] == at + 1).all()
    assert (rollout["state"][:, at + 1, X] == 0).all()


@pytest.mark.parametrize("deterministic", [False, True])
def test_a_threshold_above_the_disagreement_never_cuts(reference, deterministic):
    cut = DisagreementCut(2 * GAP, only_split_scale())
    world_model = make_world_model(DivergingMembers(2), RewardWeights(), deterministic=deterministic, cut=cut)
    rollout = ImaginedEnv(world_model, reference, origin_starts, 3).rollout(5, break_when_any_done=False)
    assert not rollout["next", "done"].any() and (rollout["next", "disagreement"][:, 2:] == GAP).all()


@pytest.mark.parametrize("deterministic", [False, True])
def test_imagination_with_the_cut_logs_branch_length_and_the_share_cut(reference, deterministic):
    n = 50
    state = torch.zeros(n, LAYOUT.size)
    next_state = state.clone()
    next_state[:, SPLIT] = torch.linspace(-1.0, 1.0, n)  # the only output that changes in the data
    transitions = TensorDict({"state": state, "next_state": next_state, "action": torch.zeros(n, 4),
                              "design": torch.full((n, 2), 0.5)}, [n])
    assert torch.equal(change_scale(transitions, LAYOUT.robot_size) > 0, only_split_scale() > 0)
    scale = float(next_state[:, SPLIT].std(correction=0))
    settings = ImaginationSettings(steps_per_batch=24, horizon=HorizonSchedule(6, 6),
                                   disagreement_cut=0.5 * GAP / scale, deterministic=deterministic,
                                   stopping=StoppingRule(kind="fixed", max_updates=1))
    imagination = Imagination(DivergingMembers(at=3), reference, RewardWeights(), settings, seed=0, episode_length=10)
    batch = next(iter(imagination.epoch(1, transitions, make_actor(18, 4))))
    assert batch.shape == (4, 6)
    metrics = imagined_metrics(batch)
    # Each row: a branch of 4 steps cut at step 3, then a fresh one truncated by the horizon after 2.
    assert metrics["imagined/branch_length"] == 3.0 and metrics["imagined/cut_share"] == 0.5
    # Only the cut step (x = 3) has members that disagree: one step of each row's six.
    assert math.isclose(metrics["imagined/disagreement"], GAP / scale / 6, rel_tol=1e-5)


def test_without_the_cut_imagination_is_unchanged(reference):
    """Off: no new keys; and a cut that never fires leaves every value and random draw as off."""
    torch.manual_seed(0)
    data = real_transitions()
    model = GaussianEnsemble(LAYOUT, 4, members=3, elites=2, hidden=(32,))
    ModelTrainer(max_epochs=2).fit(model, data, torch.Generator().manual_seed(0))
    policy = make_actor(18, 4)

    def rollout(cut):
        torch.manual_seed(1)
        starts = lambda n: data[torch.randint(data.batch_size[0], (n,))].select("state", "design")  # noqa: E731
        env = ImaginedEnv(make_world_model(model, RewardWeights(), cut=cut), reference, starts, 5)
        return env.rollout(6, policy, break_when_any_done=False)

    off = rollout(None)
    never = rollout(DisagreementCut(1e9, change_scale(data, LAYOUT.robot_size)))
    assert "disagreement" not in off["next"].keys() and "disagreement_cut" not in off.keys()
    assert not never["next", "disagreement_cut"].any()
    for key in off.keys(include_nested=True, leaves_only=True):
        assert torch.equal(off[key], never[key]), key


@pytest.mark.parametrize("deterministic", [False, True])
def test_the_imagined_env_with_the_cut_passes_torchrls_checks(reference, deterministic):
    cut = DisagreementCut(GAP / 2, only_split_scale())
    world_model = make_world_model(DivergingMembers(1), RewardWeights(), deterministic=deterministic, cut=cut)
    check_env_specs(ImaginedEnv(world_model, reference, origin_starts, batch_size=3))


@pytest.mark.parametrize("kind", ["pce", "moe"])
def test_deterministic_steps_with_the_cut_are_the_uncut_steps_and_their_disagreement_the_measured_one(reference,
                                                                                                      kind):
    """The shared all-member prediction changes nothing but the cost: every step is the uncut
    deterministic step (bit for bit for the PCE, whose every-member prediction is the same
    arithmetic), and its disagreement is MemberDisagreement's of that step."""
    torch.manual_seed(0)
    data = real_transitions()
    model = (PCEDynamics(LAYOUT, 4, order=2, members=3) if kind == "pce"
             else GaussianEnsemble(LAYOUT, 4, members=3, elites=2, hidden=(32,)))
    trainer = ClosedFormTrainer() if kind == "pce" else ModelTrainer(max_epochs=2)
    trainer.fit(model, data, torch.Generator().manual_seed(0))
    policy = make_actor(18, 4)
    scale = change_scale(data, LAYOUT.robot_size)

    def rollout(cut):
        torch.manual_seed(1)
        starts = lambda n: data[torch.randint(data.batch_size[0], (n,))].select("state", "design")  # noqa: E731
        env = ImaginedEnv(make_world_model(model, RewardWeights(), deterministic=True, cut=cut), reference,
                                starts, 5)
        return env.rollout(6, policy, break_when_any_done=False)

    uncut, shared = rollout(None), rollout(DisagreementCut(1e9, scale))
    assert isinstance(make_world_model(model, RewardWeights(), deterministic=True, cut=DisagreementCut(1e9, scale))
                      .dynamics.module, PredictAndMeasureDisagreement)
    same = torch.testing.assert_close if kind == "moe" else (lambda a, b: torch.equal(a, b) or pytest.fail(kind))
    for key in uncut.keys(include_nested=True, leaves_only=True):
        same(shared[key], uncut[key])
    measured = MemberDisagreement(model, scale)(uncut["state"].reshape(-1, LAYOUT.size),
                                                uncut["action"].reshape(-1, 4), uncut["design"].reshape(-1, 2))
    torch.testing.assert_close(shared["next", "disagreement"].reshape(-1, 1), measured)
    assert (measured > 0).all()


def test_the_pce_predicts_every_member_at_once_as_it_predicts_each():
    data = real_transitions()
    model = PCEDynamics(LAYOUT, 4, order=2, members=3)
    n = data.batch_size[0]
    model.fit(data, torch.arange(n - 20), torch.arange(n - 20, n), oversampling=4.0,
              generator=torch.Generator().manual_seed(0))
    state, action, design = data["state"][:7], data["action"][:7], data["design"][:7]
    every = member_predictions(model, state, action, design)
    assert every.shape == (3, 7, LAYOUT.size)
    for k in range(3):
        each = model.predict(state, action, design, torch.full((7,), k), deterministic=True)
        torch.testing.assert_close(every[k], each)
    assert (every.std(0) > 0).any()  # the bootstrap members differ


# The two settings that read the members' disagreement (the cut here, the penalty in
# test_disagreement_penalty.py): what each does, as its refusals name it.
DISAGREEMENT_SETTINGS = {"disagreement_cut": "cuts branches", "disagreement_penalty": "lowers the reward"}


@pytest.mark.parametrize("setting", sorted(DISAGREEMENT_SETTINGS))
@pytest.mark.parametrize("bad", [0, -0.5, float("nan"), float("inf"), True, "1"])
def test_a_setting_that_is_not_a_positive_number_is_refused_by_name(setting, bad):
    with pytest.raises(ValueError, match=rf"imagination\.{setting} must be a positive number.*got"):
        ImaginationSettings(**{setting: bad})


@pytest.mark.parametrize("setting", sorted(DISAGREEMENT_SETTINGS))
def test_the_setting_is_refused_for_models_whose_members_cannot_disagree(reference, setting):
    cells = CellEnsemble(LAYOUT, 4, (0.15, 0.2), (0.4, 0.6), divisions=2, hidden=(8,))
    settings = ImaginationSettings(**{setting: 1.0}, stopping=StoppingRule(kind="fixed"))
    with pytest.raises(ValueError, match=rf"{setting} {DISAGREEMENT_SETTINGS[setting]}.*CellEnsemble cannot.*"
                                         rf"one per cell.*{setting}=null"):
        Imagination(cells, reference, RewardWeights(), settings, 0, 10)
    with pytest.raises(ValueError, match="DivergingMembers cannot.*single member"):
        Imagination(DivergingMembers(1, members=1), reference, RewardWeights(), settings, 0, 10)
