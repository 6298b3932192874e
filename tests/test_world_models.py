"""World models: the state layout, the ensembles' fit, the imagined env, the replay buffer and the imagination."""

import copy
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.collectors import (
    HorizonSchedule,
    Imagination,
    ImaginationSettings,
    RealEpochCollector,
    StoppingRule,
    TransitionBuffer,
    is_imagined,
)
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights, RobotSettings
from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss
from unipolicy_rl.world_models import (
    CellEnsemble,
    Dynamics,
    GaussianEnsemble,
    ImaginedEnv,
    ModelTrainer,
    PendingFit,
    StateLayout,
    make_world_model,
)
from unipolicy_rl.world_models.fresh_error import fresh_error

THESIS_FROM_FULL = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
# One body (position and velocity xyz), no joints: small enough to know its dynamics.
TOY = StateLayout(num_bodies=1, num_joint_values=0, state_columns=tuple(range(6)),
                  observation_columns=tuple(range(6)))


def toy_transitions(n: int, seed: int) -> TensorDict:
    """A smooth, design-dependent toy dynamics: the change depends on z, the velocities, the
    action and (l, rho), never on the base's x, y (translation invariant, as the model assumes)."""
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(n, 6, generator=g)
    state[:, :2] *= 10.0  # x, y anywhere: the model must not care
    action = torch.rand(n, 2, generator=g) * 2 - 1
    design = torch.stack([0.15 + 0.05 * torch.rand(n, generator=g), 0.4 + 0.2 * torch.rand(n, generator=g)], -1)
    drive = torch.cat([state[:, 2:], action], -1)
    change = torch.zeros(n, 6)
    change[:, :3] = 0.1 * state[:, 3:] + 0.05 * torch.tanh(action[:, :1])
    change[:, 3:] = 0.2 * torch.tanh(drive @ torch.linspace(-1, 1, 6).reshape(6, 1)) * (design[:, :1] / 0.175)
    change[:, 5] -= 0.3 * (design[:, 1] - 0.5)
    return TensorDict({"state": state, "action": action, "design": design, "next_state": state + change}, [n])


def one_step_r2(model, data: TensorDict) -> float:
    """1 - MSE / variance of the true state change, over held-out transitions."""
    member = model.draw_members(data["design"])
    predicted = model.predict(data["state"], data["action"], data["design"], member, deterministic=True)
    true_change = data["next_state"] - data["state"]
    return float(1 - ((predicted - data["next_state"]) ** 2).mean() / true_change.var(0).mean())


def test_layout_derives_the_real_envs_observation_from_its_full_state():
    env = BatchedWalkerEnv(3, full_state=True)
    env.set_seed(0)
    rollout = env.rollout(5)
    env.close()
    state = THESIS_FROM_FULL.from_full(rollout["state"])
    assert torch.equal(THESIS_FROM_FULL.observation(state, rollout["design"]), rollout["observation"])
    with_design = StateLayout.for_env(RobotSettings(), "thesis", True, "full")
    assert with_design.observation(state, rollout["design"]).shape[-1] == 20


def test_features_do_not_change_when_the_robot_is_moved_across_the_floor():
    state = torch.randn(4, THESIS_FROM_FULL.size)
    shifted = state.clone()
    bodies = THESIS_FROM_FULL.num_bodies
    for body in range(bodies):
        shifted[:, 6 * body] += 3.0  # x
        shifted[:, 6 * body + 1] -= 1.5  # y
    torch.testing.assert_close(THESIS_FROM_FULL.features(shifted), THESIS_FROM_FULL.features(state))
    assert not torch.equal(THESIS_FROM_FULL.features(state + 0.1), THESIS_FROM_FULL.features(state))


def test_a_policy_cannot_observe_more_than_the_model_predicts():
    with pytest.raises(ValueError, match="model_state='thesis'"):
        StateLayout.for_env(RobotSettings(), "full", False, "thesis")
    with pytest.raises(ValueError, match="'joints'"):
        StateLayout.for_env(RobotSettings(), "thesis", False, "joints")


def test_gaussian_ensemble_fits_a_known_dynamics_and_its_members_differ():
    torch.manual_seed(0)
    model = GaussianEnsemble(TOY, action_dim=2, members=4, elites=3, hidden=(64, 64))
    report = ModelTrainer(max_epochs=40, patience=5, batch_size=128).fit(model, toy_transitions(4000, 0),
                                                                         torch.Generator().manual_seed(0))
    held_out = toy_transitions(1000, 1)
    # Stated accuracy: the held-out one-step prediction explains >= 95% of the state change's variance.
    assert one_step_r2(model, held_out) >= 0.95, report
    assert len(report.elites) == 3 and set(report.elites) <= set(range(4))
    assert torch.argsort(report.validation_error)[:3].tolist() == report.elites
    # The members are different networks: their predictions disagree (a little) on new data.
    predictions = torch.stack([
        model.predict(held_out["state"], held_out["action"], held_out["design"], torch.full((1000,), m),
                      deterministic=True) for m in range(4)
    ])
    spread = predictions.std(0).mean()
    assert 1e-5 < spread < 0.1 * (held_out["next_state"] - held_out["state"]).std()
    # Sampled predictions carry the learned noise; deterministic ones do not.
    member = torch.zeros(1000, dtype=torch.long)
    args = (held_out["state"], held_out["action"], held_out["design"], member)
    assert not torch.equal(model.predict(*args), model.predict(*args))
    assert torch.equal(model.predict(*args, deterministic=True), model.predict(*args, deterministic=True))


@pytest.mark.slow  # (a fit of about 13 s)
def test_a_bfloat16_fit_predicts_held_out_data_as_well_as_a_float32_one_and_keeps_float32_weights():
    """precision=bfloat16 runs the training steps under autocast: the same stated accuracy as the
    float32 fit of the test above, a different path there (the steps did run in bfloat16), and the
    weights, Adam and the validation errors in float32."""
    fits = {}
    for precision in ("float32", "bfloat16"):
        torch.manual_seed(0)
        model = GaussianEnsemble(TOY, action_dim=2, members=4, elites=3, hidden=(64, 64))
        report = ModelTrainer(max_epochs=40, patience=5, batch_size=128, precision=precision).fit(
            model, toy_transitions(4000, 0), torch.Generator().manual_seed(0))
        assert all(p.dtype == torch.float32 for p in model.parameters())
        assert report.validation_error.dtype == torch.float32
        fits[precision] = (model, one_step_r2(model, toy_transitions(1000, 1)))
    assert fits["bfloat16"][1] >= 0.95 and fits["bfloat16"][1] >= fits["float32"][1] - 0.01, fits
    assert not torch.equal(next(fits["float32"][0].parameters()), next(fits["bfloat16"][0].parameters()))
    with pytest.raises(ValueError, match="precision must be one of .*'float16'"):
        ModelTrainer(precision="float16")


def test_an_auto_precision_fit_runs_in_bfloat16_only_where_the_cpu_computes_in_it(monkeypatch):
    """precision=auto: bfloat16 on a CPU with AVX512-BF16 or AMX (where it pays), float32 where autocast
    would emulate it (about 3x slower) and on other devices; the report says which ran."""
    from unipolicy_rl.world_models import trainer as trainer_module

    for native in (False, True):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda native=native: native, raising=False)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
        assert trainer_module.fit_dtype("auto", "cpu") == (torch.bfloat16 if native else None)
        torch.manual_seed(0)
        model = GaussianEnsemble(TOY, action_dim=2, members=2, elites=1, hidden=(16,))
        report = ModelTrainer(max_epochs=1, batch_size=128, precision="auto").fit(
            model, toy_transitions(500, 0), torch.Generator().manual_seed(0))
        assert report.extras["fit_bfloat16"] == float(native)
    assert trainer_module.fit_dtype("auto", "cuda") is None  # unmeasured there: float32
    assert trainer_module.fit_dtype("bfloat16", "cpu") == torch.bfloat16  # asked for by name: as asked


def test_a_fit_budgeted_in_steps_stops_there_and_a_warm_model_keeps_improving_fit_after_fit():
    """max_steps caps a fit's gradient steps (mid-epoch); the weights carry over, so short fits add up."""
    torch.manual_seed(0)
    model = GaussianEnsemble(TOY, action_dim=2, members=2, elites=1, hidden=(32, 32))
    data = toy_transitions(4000, 0)  # 3,200 training samples: 13 steps of 256 per epoch
    trainer = ModelTrainer(max_epochs=40, max_steps=20, batch_size=256)
    errors = []
    for fit in range(4):
        report = trainer.fit(model, data, torch.Generator().manual_seed(fit))
        assert report.extras["fit_steps"] == 20 and report.epochs == 2  # 13 steps, then 7 of the second epoch
        errors.append(float(report.validation_error.min()))
    assert errors[-1] < 0.5 * errors[0], errors


def test_checks_every_few_steps_end_a_warm_fit_early_however_large_the_data():
    """A model already fitted has little to learn from the same data: checked once per epoch it
    still runs patience + 1 epochs; checked every few steps it stops after as many checks."""
    torch.manual_seed(0)
    model = GaussianEnsemble(TOY, action_dim=2, members=2, elites=1, hidden=(32, 32))
    data = toy_transitions(4000, 0)  # 13 steps of 256 per epoch
    ModelTrainer(max_epochs=40, patience=5).fit(model, data, torch.Generator().manual_seed(0))
    warm = model.state_dict()
    per_epoch = ModelTrainer(max_epochs=40, patience=2, min_improvement=0.05).fit(
        model, data, torch.Generator().manual_seed(1))
    model.load_state_dict(warm)
    per_steps = ModelTrainer(max_epochs=40, patience=2, min_improvement=0.05, check_every=3).fit(
        model, data, torch.Generator().manual_seed(1))
    assert per_epoch.extras["fit_steps"] == 13 * per_epoch.epochs >= 13 * 3, per_epoch
    assert per_steps.extras["fit_steps"] < 0.5 * per_epoch.extras["fit_steps"], (per_steps, per_epoch)
    assert per_steps.extras["fit_steps"] % 3 == 0  # it stopped at a check


def test_a_check_reads_at_most_validation_rows_per_member_and_a_larger_cap_changes_nothing(monkeypatch):
    """The cap bounds what one check costs (its rows), and a cap above the held-out set is no cap:
    the same fit to the bit, so the default's runs are unchanged by the setting existing."""
    data = toy_transitions(4000, 0)  # 800 held out
    read = []
    original = GaussianEnsemble.validation_error

    def recording(self, x, y):
        read.append(x.shape[1])
        return original(self, x, y)

    monkeypatch.setattr(GaussianEnsemble, "validation_error", recording)
    fits = {}
    for cap in (None, 800, 100):
        torch.manual_seed(0)
        model = GaussianEnsemble(TOY, action_dim=2, members=2, elites=1, hidden=(32, 32))
        read.clear()
        report = ModelTrainer(max_epochs=3, patience=3, validation_rows=cap).fit(
            model, data, torch.Generator().manual_seed(0))
        fits[cap] = (set(read), report, model.state_dict())
    assert fits[None][0] == fits[800][0] == {800} and fits[100][0] == {100}
    assert torch.equal(fits[None][1].validation_error, fits[800][1].validation_error)
    assert all(torch.equal(a, b) for a, b in zip(fits[None][2].values(), fits[800][2].values(), strict=True))
    # 100 rows estimate the same error: within 30% of the whole held-out set's
    assert torch.allclose(fits[100][1].validation_error, fits[None][1].validation_error, rtol=0.3)


def test_a_background_fit_leaves_the_model_alone_until_its_result_then_matches_a_fit_done_at_once():
    """imagination.background_fit: the policy keeps training on the model as it was while the fit
    runs on a copy; result() hands over exactly the weights a fit in the loop's thread gives."""
    torch.manual_seed(0)
    start = GaussianEnsemble(TOY, action_dim=2, members=2, elites=1, hidden=(32, 32))
    data, trainer = toy_transitions(2000, 0), ModelTrainer(max_epochs=2, batch_size=256)
    at_once, behind = copy.deepcopy(start), copy.deepcopy(start)
    done = PendingFit(trainer, at_once, data, torch.Generator().manual_seed(3), background=False)
    pending = PendingFit(trainer, behind, data, torch.Generator().manual_seed(3), background=True)
    before = {name: value.clone() for name, value in start.state_dict().items()}
    # While it runs (or once it has run) the model the imagination reads is the old one ...
    assert all(torch.equal(before[name], value) for name, value in behind.state_dict().items())
    report, expected = pending.result(), done.result()
    # ... and afterwards it holds the fit: the same weights, elites and report as the fit done at once.
    assert report.elites == expected.elites
    assert torch.equal(report.validation_error, expected.validation_error)
    for name, value in at_once.state_dict().items():
        assert torch.equal(behind.state_dict()[name], value), name
    assert any(not torch.equal(before[name], value) for name, value in behind.state_dict().items())


def test_a_background_fit_that_fails_raises_in_the_loop_and_a_thread_count_is_refused():
    model = GaussianEnsemble(TOY, action_dim=2, members=2, elites=1, hidden=(8,))
    one_row = toy_transitions(1, 0)  # too few to split into training and validation rows
    pending = PendingFit(ModelTrainer(max_epochs=1), model, one_row, None, background=True)
    with pytest.raises(ValueError, match="at least 2 transitions"):
        pending.result()
    with pytest.raises(ValueError, match="world_model.trainer.num_threads=null \\(got 2\\)"):
        PendingFit(ModelTrainer(num_threads=2), model, toy_transitions(100, 0), None, background=True)


def test_cell_ensemble_trains_each_member_on_its_own_cell_only():
    torch.manual_seed(0)
    model = CellEnsemble(TOY, action_dim=2, length_range=(0.15, 0.2), density_range=(0.4, 0.6), divisions=2,
                         hidden=(32, 32))
    data = toy_transitions(2000, 0)
    cells = model.cell(data["design"])
    # Leave the (long, light) cell without data: its networks must stay as initialised.
    empty = int(model.cell(torch.tensor([[0.19, 0.45]])))
    data = data[cells != empty]
    before = [p[empty].clone() for p in model.member_parameters()]
    report = ModelTrainer(max_epochs=10, patience=3).fit(model, data, torch.Generator().manual_seed(0))
    assert report.members_without_data == 1
    assert all(torch.equal(b, p[empty]) for b, p in zip(before, model.member_parameters(), strict=True))
    assert torch.isinf(report.validation_error[empty]) and torch.isfinite(report.validation_error).sum() == 3
    # A trajectory of a design is run by its cell's member.
    assert model.draw_members(torch.tensor([[0.151, 0.41], [0.199, 0.59]])).tolist() == [0, 3]


@pytest.mark.parametrize(
    ("factory", "match"),
    [
        (lambda: GaussianEnsemble(TOY, 2, members=0), "members"),
        (lambda: GaussianEnsemble(TOY, 2, members=3, elites=4), "elites"),
        (lambda: CellEnsemble(TOY, 2, (0.15, 0.2), (0.4, 0.6), divisions=0), "divisions"),
        (lambda: HorizonSchedule(start=0), "horizon.start"),
        (lambda: StoppingRule(kind="metrpo", min_improving_fraction=0.0), "min_improving_fraction"),
        (lambda: StoppingRule(kind="sometimes"), "stopping.kind"),
        (lambda: StoppingRule(max_updates=0), "max_updates"),
        (lambda: ImaginationSettings(rollout="dream"), "rollout"),
        (lambda: ModelTrainer(patience=0), "patience"),
        (lambda: ModelTrainer(max_steps=0), "max_steps must be a positive integer or None, got 0"),
        (lambda: ModelTrainer(check_every=0), "check_every must be a positive integer or None, got 0"),
        (lambda: ModelTrainer(validation_rows=0), "validation_rows must be a positive integer or None, got 0"),
    ],
)
def test_bad_model_settings_name_the_value(factory, match):
    with pytest.raises(ValueError, match=match):
        factory()


def real_transitions() -> TensorDict:
    """120 real transitions (4 robots, 30 random steps, seed 0) with the full state."""
    torch.manual_seed(0)
    env = BatchedWalkerEnv(4, full_state=True)
    env.set_seed(0)
    rollout = env.rollout(30)
    env.close()
    return TensorDict({"state": rollout["state"], "action": rollout["action"], "design": rollout["design"],
                       "next_state": rollout["next", "state"]}, rollout.shape).reshape(-1)


def _trained_model():
    data = real_transitions()
    model = GaussianEnsemble(THESIS_FROM_FULL, 4, members=3, elites=2, hidden=(32,))
    ModelTrainer(max_epochs=3).fit(model, data, torch.Generator().manual_seed(0))
    return model, data


def _starts(data):
    return lambda n: data[torch.randint(data.batch_size[0], (n,))].select("state", "design")


def test_imagined_env_passes_torchrls_checks_and_rolls_a_policy_for_the_horizon():
    model, data = _trained_model()
    reference = BatchedWalkerEnv(1, full_state=True)
    env = ImaginedEnv(make_world_model(model, RewardWeights()), reference, _starts(data), batch_size=6)
    check_env_specs(env)
    policy = make_actor(18, 4)
    rollout = env.rollout(12, policy, break_when_any_done=False)
    assert rollout.shape == (6, 12)
    # The same keys the real env gives, the reward is the real env's reward of the predicted state.
    for key in ("observation", "design", "physics_fault", "state"):
        assert key in rollout.keys() and ("next", key) in rollout.keys(True)
    torch.testing.assert_close(rollout["next", "reward"].squeeze(-1),
                               rollout["next", "state"][..., 0] - rollout["next", "state"][..., 1].abs()
                               + rollout["next", "state"][..., 3])
    assert not rollout["next", "terminated"].any()
    reference.close()


def test_a_diverging_model_ends_the_trajectory_without_poisoning_the_batch():
    model, data = _trained_model()
    with torch.no_grad():
        model.network[-1].bias[:, :, 0] = float("nan")  # every prediction of x is NaN
    reference = BatchedWalkerEnv(1, full_state=True)
    env = ImaginedEnv(make_world_model(model, RewardWeights()), reference, _starts(data), batch_size=4)
    rollout = env.rollout(5, break_when_any_done=False)
    reference.close()
    assert rollout["next", "physics_fault"].all() and rollout["next", "truncated"].all()
    assert not rollout["next", "terminated"].any()
    assert torch.isfinite(rollout["next", "state"]).all() and torch.isfinite(rollout["next", "reward"]).all()
    # The state stays where it was, as the real env repeats its last good observation.
    torch.testing.assert_close(rollout["next", "state"], rollout["state"])


def test_truncated_branch_end_bootstraps_from_the_critic():
    """GAE on a 3-step imagined branch cut by truncation, against a hand computation."""
    critic = make_critic(1, hidden_sizes=())
    with torch.no_grad():
        critic.module[0].weight.fill_(2.0)
        critic.module[0].bias.fill_(0.5)
    loss = TRPOLoss(make_actor(1, 1), critic)
    gamma, lmbda = 0.9, 0.8
    loss.make_value_estimator(gamma=gamma, lmbda=lmbda)
    observations = torch.tensor([0.0, 1.0, 2.0, 3.0])  # s0..s3; s3 is the state after the cut
    rewards = torch.tensor([1.0, -1.0, 2.0])

    def branch(terminated_at_end: bool) -> TensorDict:
        end = torch.tensor([False, False, True]).reshape(1, 3, 1)
        return TensorDict({
            "observation": observations[:3].reshape(1, 3, 1),
            "next": {
                "observation": observations[1:].reshape(1, 3, 1),
                "reward": rewards.reshape(1, 3, 1),
                "done": end.clone(),
                "terminated": end.clone() if terminated_at_end else torch.zeros_like(end),
                "truncated": torch.zeros_like(end) if terminated_at_end else end.clone(),
            },
        }, [1, 3])

    value = 2.0 * observations + 0.5
    deltas = rewards + gamma * value[1:] - value[:3]  # truncated: V(s3) counts
    expected = torch.zeros(3)
    running = 0.0
    for t in reversed(range(3)):
        running = deltas[t] + gamma * lmbda * running
        expected[t] = running
    truncated = loss.compute_advantage(branch(False))
    torch.testing.assert_close(truncated["advantage"].reshape(3), expected)
    terminated = loss.compute_advantage(branch(True))
    # Had the branch terminated, the last step would not see V(s3).
    torch.testing.assert_close(terminated["advantage"].reshape(3)[-1], rewards[-1] - value[2])


def _tiny_model_based(stopping: StoppingRule, epochs: int = 2, deterministic: bool = False,
                      start_epochs: int | None = None, real_surrogate=None):
    """A model-based run's parts on a tiny robot batch: real epochs in a replay buffer, a model fitted
    on it each epoch, and the imagination; returns the parts and, per epoch, its imagined batches."""
    from functools import partial

    from torchrl.collectors import Collector

    from unipolicy_rl.collectors import truncate_last_step
    from unipolicy_rl.factories import training_env

    torch.manual_seed(0)
    policy = make_actor(18, 4)
    inner = Collector(partial(training_env, 2, episode_length=None, full_state=True), policy, frames_per_batch=20,
                      total_frames=20 * epochs, postproc=truncate_last_step, auto_register_policy_transforms=False)
    real = RealEpochCollector(inner, seed=0, epochs=epochs, frames_per_batch=20)
    model = GaussianEnsemble(THESIS_FROM_FULL, 4, members=3, elites=2, hidden=(16,))
    reference = BatchedWalkerEnv(1, full_state=True)
    reference.close()
    settings = ImaginationSettings(steps_per_batch=40, horizon=HorizonSchedule(4, 4), deterministic=deterministic,
                                   start_epochs=start_epochs, stopping=stopping, train_on_real=stopping.kind == "real")
    imagination = Imagination(model, reference, RewardWeights(), settings, seed=0, episode_length=10)
    buffer = TransitionBuffer(1000, model.layout.from_full)

    def epochs_of_imagination():
        with real:
            for batch in real:
                buffer.extend(batch, real.epoch)
                ModelTrainer(max_epochs=2).fit(model, buffer.contents(), torch.Generator().manual_seed(real.epoch))
                imagined = imagination.epoch(real.epoch, buffer.contents(), policy, real_surrogate)
                yield batch, imagined

    return real, buffer, model, epochs_of_imagination(), policy


def test_imagination_yields_truncated_branches_of_the_horizon_until_the_rule_stops():
    real, buffer, _, epochs, _ = _tiny_model_based(StoppingRule(kind="fixed", max_updates=3))
    shapes, counts = set(), []
    for batch, imagined in epochs:
        assert not is_imagined(batch)
        branches = list(imagined)
        counts.append(len(branches))
        for branch in branches:
            assert is_imagined(branch)
            shapes.add(tuple(branch.shape))
            assert branch["next", "truncated"][:, -1].all()  # branches end truncated, for the bootstrap
        assert imagined.metrics() == {"model/policy_updates": 3.0}
    assert counts == [3, 3]
    assert shapes == {(10, 4)}  # 40 imagined steps as 10 branches of horizon 4
    assert real.real_env_steps == 40 and len(buffer) == 40


def test_imagined_starts_can_be_kept_to_the_latest_real_epochs():
    real, buffer, _, epochs, _ = _tiny_model_based(StoppingRule(kind="fixed", max_updates=1), epochs=3, start_epochs=1)
    for _, imagined in epochs:
        batch = next(iter(imagined))
        data = buffer.contents()
        latest = data[data["collected_in"] == real.epoch]
        assert 0 < len(latest) < len(data) or real.epoch == 1
        # Every branch starts at a state of the latest epoch's real episodes.
        starts = batch["state"][:, 0]
        assert (torch.cdist(starts, latest["state"]).min(-1).values < 1e-6).all()
    with pytest.raises(ValueError, match="start_epochs must be a positive integer or None, got 0"):
        ImaginationSettings(start_epochs=0)


@pytest.mark.parametrize("deterministic", [True, False])
def test_deterministic_imagination_follows_each_members_mean_prediction(deterministic):
    _, _, model, epochs, _ = _tiny_model_based(StoppingRule(kind="fixed", max_updates=1), epochs=1,
                                            deterministic=deterministic)
    _, imagined = next(epochs)
    batch = next(iter(imagined))
    mean = model.predict(batch["state"], batch["action"], batch["design"], batch["member"].squeeze(-1),
                         deterministic=True)
    matches = torch.isclose(batch["next", "state"], mean, atol=1e-5).all(-1)
    physics = ~batch["next", "physics_fault"].squeeze(-1)  # a faulted step keeps the last state instead
    assert physics.sum() > 20
    assert matches[physics].all() if deterministic else not matches[physics].any()


def _imagined_updates(returns_per_check, monkeypatch, max_updates=10, check_every=2):
    """How many updates an epoch runs when successive checks of the members' returns give these."""
    _, _, _, epochs, _ = _tiny_model_based(StoppingRule(kind="metrpo", max_updates=max_updates, check_every=check_every,
                                                     check_starts=4, check_horizon=3), epochs=1)
    _, imagined = next(epochs)
    checks = iter(torch.tensor(r, dtype=torch.float32) for r in returns_per_check)
    monkeypatch.setattr(imagined.imagination, "member_returns", lambda policy, starts: next(checks))
    return sum(1 for _ in imagined), imagined.metrics()


def test_the_metrpo_rule_continues_while_every_member_sees_the_return_improve(monkeypatch):
    rising = [[float(k)] * 3 for k in range(10)]
    updates, metrics = _imagined_updates(rising, monkeypatch)
    assert updates == 10 and metrics["model/improving_members"] == 1.0


def test_the_metrpo_rule_stops_when_members_see_the_return_fall(monkeypatch):
    # 2 of 3 members see it fall at the first check: 1/3 < 0.7 stops the epoch after check_every updates.
    updates, metrics = _imagined_updates([[5.0, 5.0, 5.0], [6.0, 4.0, 4.0]], monkeypatch)
    assert updates == 2 and metrics["model/improving_members"] == pytest.approx(1 / 3)


def test_the_metrpo_comparison_counts_improvement_not_decline():
    rule = StoppingRule(kind="metrpo", min_improving_fraction=0.7)
    baseline = torch.tensor([1.0, 1.0, 1.0])
    assert rule.keeps_going(baseline, baseline + 1) == (True, 1.0)
    assert rule.keeps_going(baseline, baseline - 1) == (False, 0.0)
    assert rule.keeps_going(baseline, baseline) == (False, 0.0)  # no change is not an improvement


def test_metrpo_rule_stops_an_epoch_when_members_stop_seeing_improvement():
    # The policy never changes between checks, so no member sees an improvement: the rule
    # stops each epoch at its first check, after check_every updates.
    _, _, _, epochs, _ = _tiny_model_based(StoppingRule(kind="metrpo", max_updates=10, check_every=2, check_starts=4,
                                                     check_horizon=3))
    assert [sum(1 for _ in imagined) for _, imagined in epochs] == [2, 2]


def _real_checked_epoch(surrogates, max_updates=10, check_every=2, tolerance=0.0):
    """An epoch under the ``real`` rule whose successive surrogate readings are ``surrogates`` (the
    first before any update; a number: one sample's term, or a tensor of the batch's terms); each
    imagined "update" adds 1 to every weight of the policy. Returns the updates taken, the epoch's
    metrics and the policy's first weight after the epoch."""
    readings = iter(torch.as_tensor(reading, dtype=torch.float32).reshape(-1) for reading in surrogates)
    _, _, _, epochs, policy = _tiny_model_based(
        StoppingRule(kind="real", max_updates=max_updates, check_every=check_every, tolerance=tolerance),
        epochs=1, real_surrogate=lambda: next(readings))
    _, imagined = next(epochs)
    weight = next(policy.parameters())
    first = weight.detach().clone()
    taken = 0
    for _ in imagined:
        with torch.no_grad():
            for parameter in policy.parameters():
                parameter.add_(1.0)
        taken += 1
    return taken, imagined.metrics(), float((weight - first).flatten()[0])


def test_the_real_rule_keeps_updates_while_the_real_surrogate_rises_and_undoes_the_last_check_s():
    # Checks after 2 and 4 updates: a rise, then a fall: 4 updates taken, the policy back where it
    # was after 2 (every weight +2), and the gain of the kept ones reported.
    taken, metrics, moved = _real_checked_epoch([0.0, 0.3, 0.1])
    assert taken == 4 and moved == pytest.approx(2.0)
    assert metrics["model/kept_updates"] == 2.0 and metrics["model/policy_updates"] == 4.0
    assert metrics["model/real_surrogate_gain"] == pytest.approx(0.3)
    # A fall at the first check keeps none of the imagined updates.
    taken, metrics, moved = _real_checked_epoch([0.0, -0.1])
    assert taken == 2 and moved == pytest.approx(0.0) and metrics["model/kept_updates"] == 0.0
    assert metrics["model/real_surrogate_gain"] == 0.0


def test_the_real_rule_checks_the_updates_after_its_last_regular_check():
    # max_updates=5, checks every 2: after 2 and 4, and once more after the fifth, which is undone.
    taken, metrics, moved = _real_checked_epoch([0.0, 0.1, 0.2, 0.15], max_updates=5)
    assert taken == 5 and moved == pytest.approx(4.0) and metrics["model/kept_updates"] == 4.0
    # Rising to the end: all five kept.
    taken, metrics, moved = _real_checked_epoch([0.0, 0.1, 0.2, 0.3], max_updates=5)
    assert taken == 5 and moved == pytest.approx(5.0) and metrics["model/kept_updates"] == 5.0


def test_a_tolerant_real_rule_keeps_a_fall_within_the_paired_noise_and_stops_at_one_beyond_it():
    base = torch.linspace(-1.0, 1.0, 100)
    noise = torch.randn(100, generator=torch.Generator().manual_seed(0))
    noise = (noise - noise.mean()) / noise.std()  # its standard error: exactly 1 / sqrt(100) = 0.1
    best = base + 0.3
    # After 2 updates the mean rises by 0.3; after 4 it falls by 0.15 with a spread of the paired
    # change whose standard error is 0.1: 1.5 standard errors.
    fall = best - 0.15 + noise
    readings = [base, best, fall]
    taken, metrics, moved = _real_checked_epoch(readings, max_updates=4, tolerance=2.0)
    assert taken == 4 and moved == pytest.approx(4.0) and metrics["model/kept_updates"] == 4.0
    assert metrics["model/real_surrogate_gain"] == pytest.approx(0.15, abs=1e-5)  # the kept policy's, not the best's
    # The same fall with a tolerance of 1 standard error: beyond the noise, the last two undone.
    taken, metrics, moved = _real_checked_epoch(readings, max_updates=4, tolerance=1.0)
    assert taken == 4 and moved == pytest.approx(2.0) and metrics["model/kept_updates"] == 2.0
    # Kept falls are measured against the best check, not the last kept one: two falls of 1.5
    # standard errors each are 3 below the best.
    readings = [base, best, fall, fall - 0.15]
    taken, metrics, moved = _real_checked_epoch(readings, max_updates=6, tolerance=2.0)
    assert taken == 6 and moved == pytest.approx(4.0) and metrics["model/kept_updates"] == 4.0
    # Without a tolerance, today's rule: any fall stops.
    taken, metrics, moved = _real_checked_epoch([base, best, best - 0.001], max_updates=4)
    assert moved == pytest.approx(2.0)


def test_a_tolerance_is_refused_outside_the_real_rule_or_out_of_range():
    with pytest.raises(ValueError, match="stopping.tolerance=1.0 applies to stopping.kind=real only"):
        StoppingRule(kind="metrpo", tolerance=1.0)
    for bad in (-0.5, math.inf, math.nan, "2"):
        with pytest.raises(ValueError, match="stopping.tolerance must be a finite number >= 0"):
            StoppingRule(kind="real", tolerance=bad)


def test_the_real_rule_needs_the_real_batch_s_update_and_its_surrogate():
    with pytest.raises(ValueError, match="stopping.kind=real .* set train_on_real=true"):
        ImaginationSettings(stopping=StoppingRule(kind="real"))
    _, _, _, epochs, _ = _tiny_model_based(StoppingRule(kind="real"), epochs=1)
    with pytest.raises(ValueError, match="stopping.kind=real needs real_surrogate"):
        next(epochs)


def test_every_member_votes_in_the_metrpo_rule_not_only_the_elites():
    model, data = _trained_model()  # 3 members, 2 elites
    assert isinstance(model, Dynamics)
    assert model.voting_members.tolist() == [0, 1, 2] and len(model.elite_members) == 2
    reference = BatchedWalkerEnv(1, full_state=True)
    reference.close()
    returns = Imagination(model, reference, RewardWeights(), ImaginationSettings(), 0, 10).member_returns(
        make_actor(18, 4), _starts(data)(3))
    assert returns.shape == (3,)


def test_metrpo_is_refused_for_a_model_whose_members_are_design_cells():
    model = CellEnsemble(THESIS_FROM_FULL, 4, (0.15, 0.2), (0.4, 0.6), divisions=2, hidden=(8,))
    assert isinstance(model, Dynamics) and model.voting_members is None
    reference = BatchedWalkerEnv(1, full_state=True)
    reference.close()
    with pytest.raises(ValueError, match="CellEnsemble.*stopping.kind=fixed"):
        Imagination(model, reference, RewardWeights(), ImaginationSettings(stopping=StoppingRule(kind="metrpo")), 0, 10)
    Imagination(model, reference, RewardWeights(), ImaginationSettings(stopping=StoppingRule(kind="fixed")), 0, 10)


def test_device_setting_is_checked_and_auto_falls_back_to_the_cpu():
    from unipolicy_rl.device import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA GPU"):
            resolve_device("cuda")


def test_member_returns_survive_a_trajectory_that_faults():
    from unipolicy_rl.world_models import member_returns

    model, data = _trained_model()
    with torch.no_grad():
        model.network[-1].bias[:, :, 0] = float("nan")
    reference = BatchedWalkerEnv(1, full_state=True)
    returns = member_returns(make_world_model(model, RewardWeights(), deterministic=True), reference,
                             make_actor(18, 4), _starts(data)(3), horizon=4)
    reference.close()
    assert returns.shape == (3,) and torch.isfinite(returns).all()


def test_a_row_assigned_a_member_keeps_it_after_its_fault():
    """TorchRL restarts a faulted row with only the ``_reset`` mask: the row must come back under
    its own member, else a comparison across members mixes them."""
    model, data = _trained_model()
    with torch.no_grad():
        model.network[-1].bias[1, :, :] = float("nan")  # member 1 faults at every step
    reference = BatchedWalkerEnv(1, full_state=True)
    reference.close()
    starts = _starts(data)(3)
    members = torch.tensor([0, 1, 2])
    env = ImaginedEnv(make_world_model(model, RewardWeights(), deterministic=True), reference,
                            lambda k: starts[torch.arange(k) % 3], batch_size=3, members=members)
    rollout = env.rollout(4, make_actor(18, 4), break_when_any_done=False)
    assert rollout["next", "physics_fault"][1].all() and not rollout["next", "physics_fault"][[0, 2]].any()
    assert (rollout["member"].squeeze(-1) == members.unsqueeze(-1)).all()


class _ShiftedMembers:
    """A Dynamics stand-in: member m predicts the true change plus ``offsets[m]`` (per row)."""

    layout = TOY

    def __init__(self, data: TensorDict, offsets: list[torch.Tensor]) -> None:
        self.data, self.offsets, self.members = data, offsets, len(offsets)

    device = torch.device("cpu")
    voting_members = property(lambda self: torch.arange(self.members))

    def predict(self, state, action, design, member, deterministic=False):
        rows = torch.arange(len(member)) % len(self.data)  # (the rows come repeated once per member)
        return self.data["next_state"][rows] + torch.stack(self.offsets)[member, rows]


def test_fresh_error_is_the_unexplained_share_of_the_real_state_change():
    data = toy_transitions(500, 3)
    change = data["next_state"] - data["state"]
    exact = fresh_error(_ShiftedMembers(data, [torch.zeros(500, 6)] * 2), data)
    assert exact["model/fresh_error"] == pytest.approx(0.0, abs=1e-9)
    # Predicting the batch's mean change explains none of its variance: exactly 1.
    to_mean = change.mean(0) - change
    assert fresh_error(_ShiftedMembers(data, [to_mean, to_mean]), data)["model/fresh_error"] == pytest.approx(1.0)
    # A model fitted on the toy dynamics explains most of new data; an unfitted one does not.
    torch.manual_seed(0)
    model = GaussianEnsemble(TOY, action_dim=2, members=3, elites=2, hidden=(64, 64))
    unfitted = fresh_error(model, data)["model/fresh_error"]
    ModelTrainer(max_epochs=40, patience=5, batch_size=128).fit(model, toy_transitions(4000, 0),
                                                                torch.Generator().manual_seed(0))
    fitted = fresh_error(model, data)["model/fresh_error"]
    assert fitted < 0.1 and unfitted > 10 * fitted, (fitted, unfitted)


def test_fresh_spread_rank_says_whether_disagreement_tracks_the_error():
    data = toy_transitions(300, 4)
    size = torch.linspace(0.01, 1.0, 300).unsqueeze(-1).expand(300, 6)
    # Members {truth + 2e, truth}: their mean is off by e and their spread is |e|: it tracks the error.
    tracking = fresh_error(_ShiftedMembers(data, [2 * size, torch.zeros(300, 6)]), data)
    assert tracking["model/fresh_spread_rank"] == pytest.approx(1.0)
    # Members that agree most where their mean is most wrong: the spread misleads.
    misleading = _ShiftedMembers(data, [size + (1.01 - size), size - (1.01 - size)])
    assert fresh_error(misleading, data)["model/fresh_spread_rank"] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="at least 2 transitions"):
        fresh_error(_ShiftedMembers(data[:1], [torch.zeros(1, 6)]), data[:1])
