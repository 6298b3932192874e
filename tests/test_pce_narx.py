"""PC-NARX inputs of the one-step PCEs (``world_model.model.lags``): memory, fit, imagination."""

import pytest
import torch
from tensordict import TensorDict
from test_world_models import THESIS_FROM_FULL, TOY
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.collectors import transitions
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights
from unipolicy_rl.world_models import (
    ClosedFormTrainer,
    ImaginedEnv,
    PCEDynamics,
    SparsePCEDynamics,
    make_world_model,
)
from unipolicy_rl.world_models.pce.lags import MAX_LAGS, LagMemory


def delayed_batch(robots: int, steps: int, seed: int) -> TensorDict:
    """``[robots, steps]`` episodes of a toy body whose velocity answers the action of the step
    *before* (a one-step delay, zero before the episode's start) and only its z velocity the
    current one: a model without the previous action cannot know where x, y are driven."""
    g = torch.Generator().manual_seed(seed)
    action = torch.rand(robots, steps, 2, generator=g) * 2 - 1
    design = torch.stack([0.15 + 0.05 * torch.rand(robots, generator=g),
                          0.4 + 0.2 * torch.rand(robots, generator=g)], -1).unsqueeze(1).expand(robots, steps, 2)
    state = torch.zeros(robots, steps + 1, 6)
    state[:, 0, 3:] = torch.randn(robots, 3, generator=g) * 0.3
    previous = torch.zeros(robots, 2)
    for s in range(steps):
        position, velocity = state[:, s, :3], state[:, s, 3:]
        drive = torch.stack([previous[:, 0], previous[:, 1], action[:, s, 0]], -1)
        state[:, s + 1, :3] = position + 0.1 * velocity
        state[:, s + 1, 3:] = 0.8 * velocity + 0.5 * drive
        previous = action[:, s]
    return TensorDict({"state": state[:, :-1], "action": action, "design": design,
                       ("next", "state"): state[:, 1:],
                       ("next", "physics_fault"): torch.zeros(robots, steps, 1, dtype=torch.bool)},
                      [robots, steps])


def held_out_error(model, data: TensorDict) -> float:
    """Standardised one-step MSE of member 0's mean prediction of the robot's state."""
    robot = model.layout.robot_size
    predicted = model.predict(data["state"], data["action"], data["design"], torch.zeros(len(data), dtype=torch.long),
                              deterministic=True)[:, :robot]
    change = (data["next_state"] - data["state"])[:, :robot]
    return float(((predicted - data["next_state"][:, :robot]).pow(2) / change.var(0)).mean())


@pytest.mark.parametrize("model_class", [PCEDynamics, SparsePCEDynamics])
def test_a_lagged_pce_recovers_a_delayed_response_the_unlagged_one_cannot(model_class):
    errors = {}
    for lags in (0, 1):
        model = model_class(TOY, action_dim=2, order=2, truncation="total_degree", max_interaction=None,
                            interactions="all", members=1, lags=lags)
        fit = transitions(delayed_batch(40, 50, 0), TOY.from_full, model.memory_of)
        ClosedFormTrainer().fit(model, fit, torch.Generator().manual_seed(0))
        errors[lags] = held_out_error(model, transitions(delayed_batch(20, 50, 1), TOY.from_full, model.memory_of))
    # The delayed drive is linear in the previous action: the lagged model is exact up to rounding,
    # the unlagged one misses the share of the velocity change that the previous action explains.
    assert errors[1] < 1e-4 and errors[0] > 0.1, errors


def test_real_memory_is_the_previous_steps_change_and_action_and_zero_at_an_episodes_start():
    model = PCEDynamics(TOY, action_dim=2, order=1, members=1, lags=2)
    assert model.layout.memory_size == 2 * (6 + 2) and model.layout.size == 6 + 16
    batch = delayed_batch(3, 6, 0)
    # Row 1 holds two episodes: the second begins at step 3 (its first state is a reset).
    batch["next", "done"] = torch.zeros(3, 6, 1, dtype=torch.bool)
    batch["next", "done"][1, 2] = True
    before, after = model.memory_of(batch)
    change = batch["next", "state"] - batch["state"]
    action = batch["action"]
    assert (before[:, 0] == 0).all() and (before[1, 3] == 0).all()
    torch.testing.assert_close(before[0, 1], torch.cat([change[0, 0], action[0, 0], torch.zeros(8)]))
    torch.testing.assert_close(before[0, 2], torch.cat([change[0, 1], action[0, 1], change[0, 0], action[0, 0]]))
    # After the reset only the new episode's own steps enter.
    torch.testing.assert_close(before[1, 4], torch.cat([change[1, 3], action[1, 3], torch.zeros(8)]))
    torch.testing.assert_close(before[1, 5], torch.cat([change[1, 4], action[1, 4], change[1, 3], action[1, 3]]))
    # The memory after a step is the one before the next step of the same episode.
    torch.testing.assert_close(after[0, :-1], before[0, 1:])
    torch.testing.assert_close(after[1, 3:5], before[1, 4:])
    # The buffer's rows carry it: the state of step s is the robot's, then its memory.
    rows = transitions(batch, TOY.from_full, model.memory_of)
    torch.testing.assert_close(rows["state"].reshape(3, 6, -1)[..., 6:], before)


def fitted_real_model(lags: int) -> tuple[PCEDynamics, TensorDict]:
    """A linear lagged PCE on 16 real robots' 70-step episodes (enough rows for every linear term,
    the lagged ones included, in the bootstrap member that sees the fewest episodes), and the
    buffer rows it was fitted on."""
    torch.manual_seed(0)
    env = BatchedWalkerEnv(16, full_state=True)
    env.set_seed(0)
    batch = env.rollout(70)
    env.close()
    model = PCEDynamics(THESIS_FROM_FULL, 4, order=1, members=2, lags=lags)
    data = transitions(batch, THESIS_FROM_FULL.from_full, model.memory_of)
    ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))
    return model, data


class FixedActions:
    """A policy that plays ``actions[k]`` at its k-th call."""

    def __init__(self, actions: torch.Tensor) -> None:
        self.actions, self.calls = actions, 0

    def __call__(self, tensordict):
        tensordict.set("action", self.actions[self.calls])
        self.calls += 1
        return tensordict


def test_the_lagged_imagined_env_passes_torchrls_checks_and_feeds_back_its_own_predictions():
    model, data = fitted_real_model(lags=1)
    robot = model.layout.robot_size
    assert int(model.fitted_terms) == model.terms  # the lagged inputs' terms among them
    reference = BatchedWalkerEnv(1, full_state=True)
    reference.close()
    # Starts from the buffer: one at an episode's start (memory zero), one within an episode.
    starts = data[torch.tensor([0, 7])].select("state", "design")
    assert (starts["state"][0, robot:] == 0).all() and (starts["state"][1, robot:] != 0).any()
    env = ImaginedEnv(make_world_model(model, RewardWeights(), deterministic=True), reference,
                            lambda n: starts[torch.arange(n) % 2], batch_size=2)
    check_env_specs(env)
    actions = torch.rand(2, 2, 4) * 2 - 1
    rollout = env.rollout(2, FixedActions(actions), break_when_any_done=False, auto_reset=True)
    s0, s1, s2 = rollout["state"][:, 0], rollout["next", "state"][:, 0], rollout["next", "state"][:, 1]
    torch.testing.assert_close(s0, starts["state"])  # the reset keeps the real past
    member = rollout["member"][:, 0, 0]
    # By hand: each step's robot state from the model, its memory the step just taken.
    torch.testing.assert_close(s1, model.predict(s0, actions[0], starts["design"], member, deterministic=True))
    torch.testing.assert_close(s1[:, robot:], torch.cat([s1[:, :robot] - s0[:, :robot], actions[0]], -1))
    torch.testing.assert_close(s2[:, robot:], torch.cat([s2[:, :robot] - s1[:, :robot], actions[1]], -1))
    torch.testing.assert_close(s2, model.predict(s1, actions[1], starts["design"], member, deterministic=True))
    # ... and the second step read that memory: without it the prediction differs.
    forgetful = torch.cat([s1[:, :robot], torch.zeros_like(s1[:, robot:])], -1)
    assert not torch.allclose(model.predict(forgetful, actions[1], starts["design"], member, deterministic=True)[
        :, :robot], s2[:, :robot])
    # A partial reset restarts only its row, with that start's real memory.
    fresh = env.reset(rollout[:, -1]["next"].clone().set("_reset", torch.tensor([[True], [False]])))
    torch.testing.assert_close(fresh["state"][0], starts["state"][0])
    torch.testing.assert_close(fresh["state"][1], s2[1])


def test_every_member_at_once_shifts_the_memory_as_each_member_does():
    model, data = fitted_real_model(lags=2)
    rows = data[:10]
    every = model.predict_every_member(rows["state"], rows["action"], rows["design"])
    for member in range(model.members):
        each = model.predict(rows["state"], rows["action"], rows["design"], torch.full((10,), member),
                             deterministic=True)
        torch.testing.assert_close(every[member], each)


def test_without_lags_the_models_are_todays():
    for model_class, terms in ((PCEDynamics, 898), (SparsePCEDynamics, 1102)):
        model = model_class(THESIS_FROM_FULL, 4)  # the yamls' defaults
        assert model.layout is THESIS_FROM_FULL and model.memory_of(None) is None
        # The basis of conf/world_model/pce*.yaml as docs/results.md counts it.
        assert model.terms == terms and model.basis.dimension == THESIS_FROM_FULL.feature_size + 6
        lagged = model_class(THESIS_FROM_FULL, 4, lags=1)
        assert lagged.basis.dimension == model.basis.dimension + THESIS_FROM_FULL.robot_size + 4
        # The old basis is the lagged one's terms that leave the lagged inputs out, in the same order.
        old = lagged.basis.indices[(lagged.basis.indices[:, model.basis.dimension:] == 0).all(1)]
        assert torch.equal(old[:, :model.basis.dimension], model.basis.indices)
    assert LagMemory(1, 6, 2).names(["x", "y", "z", "vx", "vy", "vz"])[-1] == "action1@t-1"


@pytest.mark.parametrize("bad", [-1, 1.5, MAX_LAGS + 1, True, "1"])
@pytest.mark.parametrize("model_class", [PCEDynamics, SparsePCEDynamics])
def test_bad_lags_are_refused_by_name(model_class, bad):
    with pytest.raises(ValueError, match=rf"world_model.model.lags must be an integer in \[0, {MAX_LAGS}\].*"
                                         rf"got {bad!r}"):
        model_class(TOY, action_dim=2, lags=bad)


@pytest.mark.slow
def test_train_with_a_lagged_pce_and_the_disagreement_cut_runs_end_to_end(tmp_path):
    from test_pce import PCE_TINY
    from test_train import TINY, run_train

    result = run_train(*TINY, *PCE_TINY, "world_model.model.lags=1", "world_model.model.order=1",
                       "imagination.disagreement_cut=1.0", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "metrics.csv").read_text()
    assert "model/fresh_error" in text and "imagined/cut_share" in text


def test_bad_lags_in_the_config_are_refused_at_start_up():
    # (validate_config is train.py's first step: test_validation runs train.py on a bad override)
    from test_train import composed

    from unipolicy_rl.validation import validate_config

    with pytest.raises(ValueError, match=r"world_model.model.lags must be an integer in \[0, 2\]"):
        validate_config(composed("source=pce", "world_model.model.lags=3"))
