"""The world-model stack on an env that is not the walker: gymnasium's Pendulum-v1 through TorchRL's
GymEnv (no design, no physics fault, an action in [-2, 2]), and scripted models where the heads'
behaviour must be exact."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs import GymEnv, InitTracker, TransformedEnv
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.collectors import Imagination, ImaginationSettings, StoppingRule, TransitionBuffer
from unipolicy_rl.envs.gym_functions import (
    HopperTermination,
    InvertedPendulumTermination,
    Walker2dTermination,
    known_termination,
    pendulum_reward,
)
from unipolicy_rl.world_models import (
    LEARNED,
    ClosedFormTrainer,
    FlatLayout,
    GaussianEnsemble,
    ImaginedEnv,
    ModelTrainer,
    PCEDynamics,
    episode_starts,
    make_world_model,
)
from unipolicy_rl.world_models.layout import check_action_bounds


def pendulum(init_tracker: bool = True):
    env = GymEnv("Pendulum-v1")
    return TransformedEnv(env, InitTracker()) if init_tracker else env


def real_batch(steps: int = 400, seed: int = 0):
    env = pendulum()
    env.set_seed(seed)
    torch.manual_seed(seed)
    batch = env.rollout(steps, break_when_any_done=False)  # random actions in the spec's [-2, 2]
    return env, batch


def test_importing_the_world_models_imports_no_physics_engine():
    script = ("import sys, unipolicy_rl.world_models, unipolicy_rl.collectors, unipolicy_rl.envs.gym_functions\n"
              "print('pybullet' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "False"


def test_the_flat_layout_reads_state_and_action_bounds_off_the_env_specs():
    layout = FlatLayout.from_env(pendulum())
    assert (layout.robot_size, layout.size, layout.design_size) == (3, 3, 0)
    assert (layout.action_low, layout.action_high) == ((-2.0,), (2.0,))
    assert layout.state_key == layout.observation_key == "observation"
    action = torch.tensor([[-3.0], [-2.0], [1.0], [2.0], [5.0]])
    # Scaled by the spec: Pendulum's [-2, 2] is the model's [-1, 1], no torque cut at 1.
    torch.testing.assert_close(layout.scaled_action(action), torch.tensor([[-1.0], [-1.0], [0.5], [1.0], [1.0]]))
    torch.testing.assert_close(layout.applied_action(action), torch.tensor([[-2.0], [-2.0], [1.0], [2.0], [2.0]]))


def test_the_flat_layout_refuses_what_it_cannot_scale_by_name():
    with pytest.raises(ValueError, match="bounded action"):
        check_action_bounds((-1.0,), (math.inf,))
    with pytest.raises(ValueError, match="one low and one high"):
        check_action_bounds((-1.0, -1.0), (1.0,))
    with pytest.raises(ValueError, match="robot_size"):
        FlatLayout(0, (-1.0,), (1.0,))
    with pytest.raises(ValueError, match="no observation 'pixels'"):
        FlatLayout.from_env(pendulum(), observation_key="pixels")


def test_pendulums_known_reward_is_the_real_envs():
    _, batch = real_batch(300)
    predicted = pendulum_reward()(batch.clone()).get(("next", "reward"))
    torch.testing.assert_close(predicted, batch.get(("next", "reward")), atol=1e-4, rtol=1e-4)


def test_the_known_terminations_are_mbrl_libs_health_checks():
    def ends(module, *rows):
        return module(torch.tensor(rows, dtype=torch.float32)).squeeze(-1).tolist()

    hopper = [1.25, 0.0, *([0.0] * 9)]
    assert ends(HopperTermination(), hopper, [0.6, *hopper[1:]], [1.25, 0.3, *hopper[2:]],
                [1.25, 0.0, 150.0, *hopper[3:]], [math.nan, *hopper[1:]]) == [False, True, True, True, True]
    walker = [1.25, 0.0, *([0.0] * 15)]
    assert ends(Walker2dTermination(), walker, [0.7, *walker[1:]], [2.1, *walker[1:]],
                [1.25, -1.2, *walker[2:]]) == [False, True, True, True]
    assert ends(InvertedPendulumTermination(), [0.0, 0.1, 0.0, 0.0], [0.0, -0.25, 0.0, 0.0]) == [False, True]
    assert known_termination("Hopper-v5") is not None and known_termination("HalfCheetah-v5") is None


def test_the_buffer_keeps_a_plain_envs_steps_with_applied_actions_and_true_starts():
    env, batch = real_batch(450)  # two whole episodes of 200 steps and part of a third
    model = GaussianEnsemble(FlatLayout.from_env(env), 1, members=2, elites=1, hidden=(8,), learn=["reward"])
    buffer = TransitionBuffer.for_model(1000, model)
    rows = buffer.extend(batch, epoch=1)
    assert len(rows) == 450  # no physics_fault key: every step kept
    assert rows.get("design").shape == (450, 0)
    assert rows.get("action").abs().max() > 1.0  # Pendulum's torques kept as applied, not cut to [-1, 1]
    assert rows.get("episode_start").nonzero().squeeze(-1).tolist() == [0, 200, 400]
    torch.testing.assert_close(rows.get("reward"), batch.get(("next", "reward")))


def test_episode_starts_follow_is_init_then_trajectory_ids_then_done():
    marked = TensorDict({"is_init": torch.tensor([[False, True, False]]).unsqueeze(-1)}, [1, 3])
    assert episode_starts(marked).tolist() == [[False, True, False]]
    ids = TensorDict({("collector", "traj_ids"): torch.tensor([[4, 4, 5], [7, 8, 8]])}, [2, 3])
    assert episode_starts(ids).tolist() == [[True, False, True], [True, True, False]]
    # The row's last id in the batch before: a row that goes on from it did not begin an episode.
    assert episode_starts(ids, torch.tensor([4, 6])).tolist() == [[False, False, True], [True, True, False]]
    done = TensorDict({("next", "done"): torch.tensor([[False, True, False]]).unsqueeze(-1)}, [1, 3])
    assert episode_starts(done).tolist() == [[True, False, True]]


class Scripted(nn.Module):
    """Two members that both add 0.5 to every number; they learn the reward -x0 and terminate
    where the next x0 passes 1."""

    members = 2
    learned_outputs = ("reward", "terminated")

    def __init__(self, layout: FlatLayout, step: float = 0.5) -> None:
        super().__init__()
        self.layout, self.step = layout, step
        self.register_buffer("anchor", torch.zeros(()))

    @property
    def device(self):
        return self.anchor.device

    @property
    def voting_members(self):
        return torch.arange(self.members)

    def memory_of(self, batch):
        return None

    def draw_members(self, design, generator=None):
        return torch.zeros(design.shape[:-1], dtype=torch.long)

    def predict_outputs(self, state, action, design, member, deterministic=False):
        next_state = state + self.step
        return next_state, torch.stack([-state[..., 0], (next_state[..., 0] > 1.0).float()], dim=-1)

    def predict(self, state, action, design, member, deterministic=False):
        return self.predict_outputs(state, action, design, member, deterministic)[0]


def zero_starts(n: int) -> TensorDict:
    return TensorDict({"state": torch.zeros(n, 3)}, [n])


def test_the_imagined_env_of_a_plain_env_has_its_specs_and_no_design():
    env = pendulum(init_tracker=False)
    model = Scripted(FlatLayout.from_env(env))
    imagined = ImaginedEnv(make_world_model(model, pendulum_reward()), env, zero_starts, batch_size=3)
    assert "design" not in imagined.observation_spec.keys()
    check_env_specs(imagined)


def test_a_learned_termination_terminates_and_a_blow_up_truncates():
    env = pendulum(init_tracker=False)
    model = Scripted(FlatLayout.from_env(env))
    world = make_world_model(model, LEARNED, termination=LEARNED)
    rollout = ImaginedEnv(world, env, zero_starts, batch_size=2).rollout(4, break_when_any_done=False)
    # x0: 0 -> 0.5 -> 1.0 -> 1.5 (terminated, the row restarts at 0) -> 0.5
    assert rollout["next", "terminated"][0].squeeze(-1).tolist() == [False, False, True, False]
    assert not rollout["next", "truncated"].any()
    torch.testing.assert_close(rollout["next", "reward"][0].squeeze(-1), torch.tensor([0.0, -0.5, -1.0, 0.0]))
    # The blow-up limit is a setting: past it the step is a fault, truncated, never terminated.
    world = make_world_model(model, LEARNED, termination=LEARNED, blowup_limit=0.75)
    rollout = ImaginedEnv(world, env, zero_starts, batch_size=2).rollout(2, break_when_any_done=False)
    assert rollout["next", "physics_fault"][0].squeeze(-1).tolist() == [False, True]
    assert rollout["next", "truncated"][0].squeeze(-1).tolist() == [False, True]
    assert not rollout["next", "terminated"].any()


def test_a_known_reward_reads_the_real_envs_keys_in_imagination():
    env = pendulum(init_tracker=False)
    model = Scripted(FlatLayout.from_env(env))
    rollout = ImaginedEnv(make_world_model(model, pendulum_reward()), env, zero_starts, 4).rollout(3)
    expected = pendulum_reward()(rollout.clone()).get(("next", "reward"))
    torch.testing.assert_close(rollout["next", "reward"], expected)


def test_a_learned_reward_or_termination_needs_a_model_that_learns_it():
    env = pendulum(init_tracker=False)
    model = GaussianEnsemble(FlatLayout.from_env(env), 1, members=2, elites=1, hidden=(8,))
    with pytest.raises(ValueError, match=r"learn=\['reward'\]"):
        make_world_model(model, LEARNED)
    with pytest.raises(ValueError, match=r"learn=\['terminated'\]"):
        make_world_model(model, pendulum_reward(), termination=LEARNED)
    with pytest.raises(ValueError, match="learn must name"):
        GaussianEnsemble(FlatLayout.from_env(env), 1, learn=["value"])


def test_an_ensemble_learns_pendulums_reward_beside_its_state():
    env, batch = real_batch(2000)
    torch.manual_seed(0)
    model = GaussianEnsemble(FlatLayout.from_env(env), 1, members=3, elites=2, hidden=(64, 64), learn=["reward"])
    buffer = TransitionBuffer.for_model(10_000, model)
    buffer.extend(batch, epoch=1)
    ModelTrainer(max_epochs=60, patience=10).fit(model, buffer.contents(), torch.Generator().manual_seed(0))
    rows = buffer.contents()[:500]
    state, learned = model.predict_outputs(rows["state"], rows["action"], rows["design"],
                                           torch.zeros(500, dtype=torch.long), deterministic=True)
    truth = rows["reward"].squeeze(-1)
    # Rewards run from about -16 to 0: a head that learned nothing errs by their spread (about 3.7).
    assert (learned.squeeze(-1) - truth).abs().mean() < 0.25 * truth.std()
    assert (state - rows["next_state"]).abs().mean() < 0.25 * (rows["next_state"] - rows["state"]).abs().mean()


def test_an_ensemble_predicts_the_next_state_itself_where_asked_and_learns_it():
    env, batch = real_batch(2000)
    layout = FlatLayout.from_env(env)
    buffer = TransitionBuffer.for_model(10_000, GaussianEnsemble(layout, 1, members=1, elites=1, hidden=(8,)))
    buffer.extend(batch, epoch=1)
    rows = buffer.contents()
    members = torch.zeros(500, dtype=torch.long)
    # The targets are what the option says; a head whose mean is the target's own mean predicts that
    # mean as the next state (next_state), or adds it to the state (change).
    for target in ("change", "next_state"):
        model = GaussianEnsemble(layout, 1, members=1, elites=1, hidden=(8,), target=target)
        targets = model.targets(rows["state"], rows["next_state"])
        expected = rows["next_state"] - rows["state"] if target == "change" else rows["next_state"]
        torch.testing.assert_close(targets, expected)
        model.fit_normalizers(model.inputs(rows["state"], rows["action"], rows["design"]), targets)
        for parameter in model.network[-1].parameters():
            nn.init.zeros_(parameter)
        predicted = model.predict(rows["state"][:500], rows["action"][:500], rows["design"][:500], members, True)
        mean = targets.mean(0)
        torch.testing.assert_close(predicted, mean.expand(500, -1) if target == "next_state"
                                   else rows["state"][:500] + mean, atol=1e-4, rtol=1e-4)
    torch.manual_seed(0)
    model = GaussianEnsemble(layout, 1, members=3, elites=2, hidden=(64, 64), target="next_state")
    ModelTrainer(max_epochs=60, patience=10).fit(model, rows, torch.Generator().manual_seed(0))
    state = model.predict(rows["state"][:500], rows["action"][:500], rows["design"][:500], members, True)
    assert (state - rows["next_state"][:500]).abs().mean() < 0.25 * (rows["next_state"] - rows["state"]).abs().mean()
    with pytest.raises(ValueError, match="target must be one of .*'delta'"):
        GaussianEnsemble(layout, 1, target="delta")


def fitted_plain_model(reward: str):
    """Pendulum's env, a small ensemble fitted on 400 of its real steps (learning the reward where
    ``reward`` is learned) and its buffer, with the transitions it was given."""
    env, batch = real_batch(400)
    learn = ["reward"] if reward == LEARNED else []
    model = GaussianEnsemble(FlatLayout.from_env(env), 1, members=3, elites=2, hidden=(16,), learn=learn)
    buffer = TransitionBuffer.for_model(10_000, model)
    fresh = buffer.extend(batch, epoch=1)
    ModelTrainer(max_epochs=2).fit(model, buffer.contents(), torch.Generator().manual_seed(0))
    return env, model, buffer, fresh


@pytest.mark.parametrize("reward", ["known", LEARNED])
def test_imagination_and_its_metrpo_rule_run_on_a_plain_env(reward):
    env, model, buffer, _ = fitted_plain_model(reward)
    settings = ImaginationSettings(steps_per_batch=60, stopping=StoppingRule(max_updates=2, check_every=1,
                                                                            check_starts=4, check_horizon=3))
    imagination = Imagination(model, env, LEARNED if reward == LEARNED else pendulum_reward(), settings, 0, 200)
    from unipolicy_rl.networks import make_actor

    batches = list(imagination.epoch(1, buffer.contents(), make_actor(3, 1)))
    assert 1 <= len(batches) <= 2
    for rollout in batches:
        # What SAC (the MBPO path) and TRPO read of an imagined batch, in the real env's keys.
        for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
                    ("next", "terminated")):
            assert key in rollout.keys(include_nested=True)
        assert torch.isfinite(rollout["next", "reward"]).all()


def test_a_polynomial_chaos_model_fits_and_predicts_a_plain_env():
    env, batch = real_batch(1500)
    model = PCEDynamics(FlatLayout.from_env(env), 1, order=3, members=2)
    buffer = TransitionBuffer.for_model(10_000, model)
    buffer.extend(batch, epoch=1)
    report = ClosedFormTrainer().fit(model, buffer.contents(), torch.Generator().manual_seed(0))
    assert torch.isfinite(report.validation_error).all()
    rows = buffer.contents()[:200]
    predicted = model.predict(rows["state"], rows["action"], rows["design"], torch.zeros(200, dtype=torch.long),
                              deterministic=True)
    change = (rows["next_state"] - rows["state"]).abs().mean()
    assert (predicted - rows["next_state"]).abs().mean() < 0.2 * change


def test_models_of_design_cells_refuse_an_env_without_a_design():
    from unipolicy_rl.world_models import CellEnsemble, ThesisPCEDynamics

    layout = FlatLayout(3, (-2.0,), (2.0,))
    with pytest.raises(ValueError, match="CellEnsemble keeps one member per cell"):
        CellEnsemble(layout, 1, (0.1, 0.2), (0.5, 1.5))
    with pytest.raises(ValueError, match="ThesisPCEDynamics keeps one member per cell"):
        ThesisPCEDynamics(layout, 1, (0.1, 0.2), (0.5, 1.5))


@pytest.mark.parametrize("reward", ["known", LEARNED])
def test_the_disagreement_cut_and_the_fresh_error_work_on_a_plain_env(reward):
    from unipolicy_rl.networks import make_actor
    from unipolicy_rl.world_models.fresh_error import fresh_error

    env, model, buffer, fresh = fitted_plain_model(reward)
    assert all(math.isfinite(value) for value in fresh_error(model, fresh).values())
    # A tiny threshold: (almost) every branch is cut at its first step, truncated.
    settings = ImaginationSettings(steps_per_batch=40, deterministic=True, disagreement_cut=1e-6,
                                   stopping=StoppingRule(kind="fixed", max_updates=1))
    imagination = Imagination(model, env, LEARNED if reward == LEARNED else pendulum_reward(), settings, 0, 200)
    (rollout,) = list(imagination.epoch(1, buffer.contents(), make_actor(3, 1)))
    cut = rollout["next", "disagreement_cut"]
    assert cut.float().mean() > 0.9
    assert (rollout["next", "truncated"] | ~cut).all() and not rollout["next", "terminated"].any()
