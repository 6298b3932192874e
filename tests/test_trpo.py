"""Tests for TRPOLoss and the natural-gradient update (small synthetic TensorDicts, no env)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.cpu_speed.plain_mlp import PlainMLPRegression
from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import (
    TRPOLoss,
    TRPOUpdater,
    TrustRegion,
    fit_critic,
    kl_hessian_vector_product_fn,
    make_critic_optimizer,
    natural_gradient_step,
    policy_fisher_vector_product_fn,
)
from unipolicy_rl.objectives import natural_gradient as ng


@pytest.fixture(autouse=True)
def _single_thread_and_seed():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(threads)


def make_loss(obs_dim=3, action_dim=2, hidden=(8,), dtype=torch.float32) -> TRPOLoss:
    actor = make_actor(obs_dim, action_dim, hidden).to(dtype)
    critic = make_critic(obs_dim, hidden).to(dtype)
    return TRPOLoss(actor, critic)


def collect(loss: TRPOLoss, observation: torch.Tensor, reward_fn=None, done_every: int = 0) -> TensorDict:
    """A batch as a collector would write it: actions sampled by the actor, with loc/scale."""
    batch = TensorDict(observation=observation, batch_size=observation.shape[:-1])
    with (
        torch.no_grad(),
        set_exploration_type(ExplorationType.RANDOM),
        loss.actor_network_params.to_module(loss.actor_network),
    ):
        loss.actor_network(batch)
    if reward_fn is None:
        reward = torch.randn(*batch.shape, 1, dtype=observation.dtype)
    else:
        reward = reward_fn(batch)
    done = torch.zeros(*batch.shape, 1, dtype=torch.bool)
    if done_every:
        done[..., done_every - 1 :: done_every, :] = True
    else:
        done[:] = True  # one-step episodes
    batch["next"] = TensorDict(
        observation=torch.randn_like(observation),
        reward=reward,
        done=done,
        terminated=done.clone(),
        batch_size=batch.shape,
    )
    return batch


def snapshot(params):
    return [p.detach().clone() for p in params]


def all_equal(params, copies) -> bool:
    return all(torch.equal(p, c) for p, c in zip(params, copies, strict=True))


# -------------------------------------------------------------------------- (1) Fisher product
def test_fisher_vector_product_matches_explicit_kl_hessian():
    loss = make_loss(obs_dim=3, action_dim=2, hidden=(4,), dtype=torch.float64)
    params = loss.actor_parameters()
    with torch.no_grad():  # move away from the initialisation (tiny output layer, std 1)
        for param in params:
            param.add_(0.3 * torch.randn_like(param))
    batch = collect(loss, torch.randn(7, 3, dtype=torch.float64))

    dist_params = loss.policy_distribution_params(batch)
    reference = loss.distribution_from_params(dist_params.detach())
    kl = loss.mean_kl(reference, loss.distribution_from_params(dist_params))
    damping = 0.1
    fvp = policy_fisher_vector_product_fn(loss, dist_params, reference, damping=0.0)
    fvp_damped = policy_fisher_vector_product_fn(loss, dist_params, reference, damping=damping)
    double_backward = kl_hessian_vector_product_fn(kl, params, damping=0.0)

    keys = list(loss.actor_network_params.keys(True, True))
    shapes = [loss.actor_network_params.get(key).shape for key in keys]
    inputs = batch.select("observation")

    def kl_of_flat(flat: torch.Tensor) -> torch.Tensor:
        chunks = flat.split([math.prod(shape) for shape in shapes])
        flat_params = TensorDict({}, [])
        for key, shape, chunk in zip(keys, shapes, chunks, strict=True):
            flat_params.set(key, chunk.view(shape))
        with flat_params.to_module(loss.actor_network):
            dist = loss.actor_network.build_dist_from_params(loss.actor_network.get_dist_params(inputs.clone()))
        return loss.mean_kl(reference, dist)

    flat0 = torch.cat([p.detach().reshape(-1) for p in params])
    hessian = torch.autograd.functional.hessian(kl_of_flat, flat0)
    n = flat0.numel()
    assert n == sum(p.numel() for p in params)
    identity = torch.eye(n, dtype=torch.float64)
    fisher = torch.stack([fvp(column) for column in identity], 1)
    textbook = torch.stack([double_backward(column) for column in identity], 1)

    torch.testing.assert_close(fisher, hessian, atol=1e-10, rtol=1e-7)
    torch.testing.assert_close(textbook, hessian, atol=1e-10, rtol=1e-7)
    eigenvalues = torch.linalg.eigvalsh((hessian + hessian.T) / 2)
    assert eigenvalues.min() > -1e-10, "the KL Hessian at the current point must be PSD"
    assert eigenvalues.max() > 1e-3, "a zero Hessian would mean the KL graph is mis-built"
    damped = torch.stack([fvp_damped(column) for column in identity], 1)
    assert torch.linalg.eigvalsh((damped + damped.T) / 2).min() >= damping - 1e-9
    v = torch.randn(n, dtype=torch.float64)
    assert v @ fvp_damped(v) > 0


def test_log_std_is_optimised():
    loss = make_loss()
    log_std = next(p for name, p in loss.actor_network_params.items(True, True) if "scale" in str(name))
    assert any(p is log_std for p in loss.actor_parameters())
    batch = collect(loss, torch.randn(256, 3))
    before = log_std.detach().clone()
    result = natural_gradient_step(loss, batch)
    assert result.accepted, result.skip_reason
    assert not torch.equal(before, log_std)


# ----------------------------------------------------------------------- (2) accepted step
def test_accepted_step_respects_trust_region_and_improves_surrogate():
    loss = make_loss(obs_dim=4, action_dim=2, hidden=(16, 16))
    batch = collect(loss, torch.randn(8, 64, 4), done_every=16)
    loss.compute_advantage(batch)
    before = loss(batch)
    assert before["kl"].abs() < 1e-6  # data collected by this very policy
    max_kl = 0.01

    result = natural_gradient_step(loss, batch, trust_region=TrustRegion(max_kl=max_kl))

    assert result.accepted and result.skip_reason is None
    after = loss(batch)
    assert 0 < after["kl"] <= max_kl  # KL to the stored (old) loc/scale, computed afresh
    assert after["kl"].item() == pytest.approx(result.kl, rel=1e-4)
    improvement = (before["loss_objective"] - after["loss_objective"]).item()
    assert improvement > 0
    assert improvement == pytest.approx(result.surrogate_improvement, rel=1e-3)
    assert result.expected_improvement > 0 and result.step_norm > 0
    assert 1 <= result.line_search_tries <= 10 and 1 <= result.cg_iterations <= 10
    assert result.curvature > 0
    # The quadratic (Fisher) model sized the step, so the true KL is close to its prediction
    # (a mis-built KL graph gives a wrong curvature and misses this by orders of magnitude).
    predicted_kl = max_kl * 0.8 ** (2 * (result.line_search_tries - 1))
    assert 0.4 * predicted_kl < result.kl <= 1.5 * predicted_kl


# ----------------------------------------------------------------------- (3) rejected steps
def test_rejected_line_search_restores_parameters_bit_identically(monkeypatch):
    loss = make_loss()
    batch = collect(loss, torch.randn(128, 3))
    params = loss.actor_parameters()
    original = snapshot(params)
    solve = ng.conjugate_gradient

    def downhill(*args, **kwargs):  # a direction that can only lower the surrogate
        direction, iterations = solve(*args, **kwargs)
        return -direction, iterations

    monkeypatch.setattr(ng, "conjugate_gradient", downhill)
    result = natural_gradient_step(loss, batch, trust_region=TrustRegion(max_backtracks=10))

    assert not result.accepted
    assert "line search" in result.skip_reason
    assert result.line_search_tries == 10
    assert all_equal(params, original)


def test_non_positive_curvature_skips_without_touching_parameters(monkeypatch):
    loss = make_loss()
    batch = collect(loss, torch.randn(64, 3))
    params = loss.actor_parameters()
    original = snapshot(params)
    # A "Fisher" product that is negative definite, as a mis-built KL graph can give.
    monkeypatch.setattr(ng, "fisher_vector_product_fn", lambda *args: lambda v: -v)

    result = natural_gradient_step(loss, batch)

    assert not result.accepted and "curvature" in result.skip_reason
    assert all_equal(params, original)


def test_non_finite_advantage_skips_without_touching_parameters():
    loss = make_loss()
    batch = collect(loss, torch.randn(64, 3))
    params = loss.actor_parameters()
    original = snapshot(params)
    advantage = torch.randn(64)
    advantage[3] = float("nan")

    result = natural_gradient_step(loss, batch, advantage=advantage)

    assert not result.accepted and "non-finite" in result.skip_reason
    assert all_equal(params, original)


# ----------------------------------------------------------------------- (4) it learns
def test_trpo_solves_a_contextual_bandit():
    """One-step episodes, reward -(a - a*(x))^2 with a*(x) = W x + c, through GAE + updater.

    The optimal policy mean is a*(x). Starting from a mean of ~0 (mean absolute error ~0.4),
    TRPO must bring the mean within 0.05 of a* on held-out contexts (it reaches ~0.01). With
    the gradient sign flipped every line search fails and the error stays ~0.4.
    """
    weight = torch.tensor([[0.5, -0.3], [0.2, 0.4]])
    bias = torch.tensor([0.3, -0.4])

    def optimum(observation):
        return observation @ weight.T + bias

    def reward(batch):
        error = batch["action"] - optimum(batch["observation"])
        return -(error**2).sum(-1, keepdim=True)

    loss = make_loss(obs_dim=2, action_dim=2, hidden=(16,))
    updater = TRPOUpdater(loss, trust_region=TrustRegion(max_kl=0.05), critic_lr=1e-2, critic_epochs=5,
                          critic_minibatch_size=64)
    test_obs = torch.rand(512, 2) * 2 - 1

    def mean_error():
        with torch.no_grad():
            loc = loss.policy_distribution_params(TensorDict(observation=test_obs))["loc"]
        return (loc - optimum(test_obs)).abs().mean().item()

    initial_error = mean_error()
    accepted = 0
    for _ in range(40):
        batch = collect(loss, torch.rand(1, 512, 2) * 2 - 1, reward_fn=reward)
        metrics = updater.update(batch)
        accepted += metrics["train/step_accepted"]
        assert metrics["train/kl"] <= 0.05 + 1e-6
    final_error = mean_error()

    assert initial_error > 0.3
    assert final_error < 0.05, f"policy mean error {final_error:.3f} (started {initial_error:.3f})"
    assert accepted >= 30


# ----------------------------------------------------------------------- (5) one sample
def test_batch_of_one_sample_gives_no_nan():
    loss = make_loss()
    batch = collect(loss, torch.randn(1, 3))
    out = loss(batch.clone())
    for key in ("loss_objective", "loss_critic", "kl", "entropy"):
        assert torch.isfinite(out[key]), key

    updater = TRPOUpdater(loss)
    metrics = updater.update(collect(loss, torch.randn(1, 1, 3)))
    assert all(math.isfinite(value) for value in metrics.values()), metrics
    assert all(torch.isfinite(p).all() for p in loss.parameters())


def test_advantage_normalisation_and_constant_advantage():
    loss = make_loss()
    batch = collect(loss, torch.randn(32, 3))
    batch["advantage"] = 5.0 + 2.0 * torch.randn(32, 1)
    advantage = loss.advantage(batch)
    assert advantage.shape == (32,)
    assert advantage.mean().abs() < 1e-5 and (advantage.std() - 1).abs() < 1e-4
    batch["advantage"] = torch.full((32, 1), 3.0)  # std 0: must not divide by zero
    assert torch.isfinite(loss.advantage(batch)).all()
    result = natural_gradient_step(loss, batch)
    assert result.skip_reason == "zero policy gradient"


def test_advantages_standardised_within_groups_give_each_group_the_same_weight():
    """Two robots in one batch, one whose advantages are 100 times the other's: over the batch the
    small one's are nearly zero; within groups each has zero mean and unit std, and the step's
    gradient then draws on both."""
    loss = make_loss()
    grouped = make_loss()
    grouped.advantage_groups = "morphology"
    batch = collect(loss, torch.randn(40, 3))
    morphology = torch.tensor([0] * 24 + [3] * 15 + [7]).unsqueeze(-1)
    batch["morphology"] = morphology
    raw = torch.randn(40, 1)
    raw[:24] = 100.0 * raw[:24] + 50.0
    batch["advantage"] = raw
    over_batch = loss.advantage(batch)
    within = grouped.advantage(batch)
    assert over_batch[24:39].std() < 0.05  # drowned by the first robot's scale
    for members in (slice(0, 24), slice(24, 39)):
        assert within[members].mean().abs() < 1e-5 and (within[members].std() - 1).abs() < 1e-4
    assert within[39] == 0  # a group of one sample is centred
    # Within-group standardisation is what the step sees: the same as standardising each group alone.
    alone = (raw[24:39, 0] - raw[24:39, 0].mean()) / raw[24:39, 0].std()
    torch.testing.assert_close(within[24:39], alone, atol=1e-5, rtol=0)
    # The step still respects its KL bound.
    result = natural_gradient_step(grouped, batch, trust_region=TrustRegion(max_kl=0.01))
    assert result.accepted and 0 < result.kl <= 0.01


def test_advantage_groups_missing_from_the_batch_are_named():
    loss = make_loss()
    loss.advantage_groups = "morphology"
    batch = collect(loss, torch.randn(8, 3))
    batch["advantage"] = torch.randn(8, 1)
    with pytest.raises(KeyError, match="within the groups of morphology, which the batch does not have"):
        loss.advantage(batch)


def test_an_entropy_bonus_raises_the_std_where_the_surrogate_has_nothing_to_improve():
    """With a constant advantage the surrogate's gradient is zero: plain TRPO skips the step,
    while a bonus on the entropy moves the log-std up, within the trust region."""
    plain = make_loss()
    bonus = make_loss()
    bonus.entropy_coeff = 0.05
    bonus.load_state_dict(plain.state_dict())
    batch = collect(plain, torch.randn(64, 3))
    plain.compute_advantage(batch)
    batch["advantage"] = torch.full((64, 1), 3.0)
    assert natural_gradient_step(plain, batch).skip_reason == "zero policy gradient"
    entropy_before = bonus.policy_distribution(batch).entropy().mean()
    result = natural_gradient_step(bonus, batch, trust_region=TrustRegion(max_kl=0.01))
    assert result.accepted, result.skip_reason
    assert 0 < result.kl <= 0.01
    gained = bonus.policy_distribution(batch).entropy().mean() - entropy_before
    assert gained > 0 and result.surrogate_improvement == pytest.approx(0.05 * gained.item(), rel=1e-3)
    out = bonus(batch)
    assert out["loss_entropy"].item() == pytest.approx(-0.05 * out["entropy"].item())


def test_without_an_entropy_bonus_the_objective_is_the_surrogate_bit_for_bit():
    loss = make_loss()
    batch = collect(loss, torch.randn(8, 16, 3), done_every=4)
    advantage = loss.advantage(batch)
    distribution = loss.policy_distribution(batch)
    assert torch.equal(loss.objective(distribution, batch, advantage),
                       loss.surrogate_advantage(distribution, batch, advantage))
    assert loss(batch)["loss_entropy"].item() == 0.0


@pytest.mark.parametrize("value", [-0.01, math.nan, math.inf, True, "0.1"])
def test_a_bad_entropy_coeff_is_refused_by_name(value):
    with pytest.raises(ValueError, match="entropy_coeff"):
        TRPOLoss(make_actor(3, 2, (8,)), make_critic(3, (8,)), entropy_coeff=value)


# ----------------------------------------------------------------------- (6) set_keys
def test_set_keys_renames_what_the_loss_reads_and_writes():
    loss = make_loss()
    loss.set_keys(advantage="adv", value_target="v_target", sample_log_prob="logp_old")
    assert loss.tensor_keys.advantage == "adv"
    batch = collect(loss, torch.randn(8, 16, 3), done_every=4)
    batch.rename_key_("action_log_prob", "logp_old")

    loss.compute_advantage(batch)
    assert "adv" in batch.keys() and "v_target" in batch.keys()
    assert "advantage" not in batch.keys()
    assert "logp_old" in loss.in_keys
    out = loss(batch)
    assert torch.isfinite(out["loss_objective"]) and torch.isfinite(out["loss_critic"])
    assert natural_gradient_step(loss, batch.reshape(-1)).accepted

    del batch["logp_old"]
    with pytest.raises(KeyError):
        loss(batch)


def test_value_estimator_defaults_and_override():
    loss = make_loss()
    estimator = loss.value_estimator
    assert type(estimator).__name__ == "GAE"
    assert float(estimator.gamma) == pytest.approx(0.99)
    assert float(estimator.lmbda) == pytest.approx(0.95)
    loss.make_value_estimator(gamma=0.9, lmbda=0.97)
    assert float(loss.value_estimator.lmbda) == pytest.approx(0.97)


# ----------------------------------------------------------------------- (7) critic fit
def test_fit_critic_reduces_critic_loss():
    loss = make_loss(obs_dim=3, hidden=(32, 32))
    # One-step episodes with a smooth reward: the value target is a function to learn.
    batch = collect(loss, torch.randn(512, 3), reward_fn=lambda b: b["observation"].sin().sum(-1, True))
    loss.compute_advantage(batch)
    with torch.no_grad():
        before = loss.critic_loss(batch).item()
    optimizer = make_critic_optimizer(loss, lr=3e-3)
    generator = torch.Generator().manual_seed(1)

    result = fit_critic(loss, batch, optimizer, 20, 64, generator)

    with torch.no_grad():
        after = loss.critic_loss(batch).item()
    assert result.fitted and result.skip_reason is None and math.isfinite(result.loss)
    assert after < 0.5 * before


def test_fit_critic_fast_path_matches_autograd_and_optimizer_step(monkeypatch):
    """The hand-written MLP backward (cpu_speed) and the fused Adam kernel fit what autograd and torch's
    default Adam kernel fit: the same weights to float rounding (the order of operations differs)."""
    fast = make_loss(obs_dim=3, hidden=(16, 16))
    plain = make_loss(obs_dim=3, hidden=(16, 16))
    plain.load_state_dict(fast.state_dict())
    batch = collect(fast, torch.randn(300, 3))
    fast.compute_advantage(batch)

    fast_loss = fit_critic(fast, batch, make_critic_optimizer(fast), 3, 64, torch.Generator().manual_seed(0)).loss

    monkeypatch.setattr(PlainMLPRegression, "from_critic", classmethod(lambda cls, m: None))
    plain_optimizer = torch.optim.Adam(plain.critic_parameters(), lr=1e-3)  # torch's default kernel
    assert make_critic_optimizer(fast).defaults["fused"] and not plain_optimizer.defaults["fused"]
    plain_loss = fit_critic(plain, batch, plain_optimizer, 3, 64, torch.Generator().manual_seed(0)).loss

    assert fast_loss == pytest.approx(plain_loss, rel=1e-5)
    for fast_param, plain_param in zip(fast.critic_parameters(), plain.critic_parameters(), strict=True):
        torch.testing.assert_close(fast_param, plain_param, atol=1e-6, rtol=1e-5)


# ----------------------------------------------------------------------- (8) non-finite guards
def optimizer_state_copy(optimizer):
    return [{name: value.clone() for name, value in state.items()} for state in optimizer.state.values()]


def assert_optimizer_state_equal(optimizer, copies):
    assert len(optimizer.state) == len(copies)
    for state, copy in zip(optimizer.state.values(), copies, strict=True):
        assert state.keys() == copy.keys()
        assert all(torch.equal(state[name], copy[name]) for name in state)


def test_nan_value_target_skips_critic_fit_and_counts_consecutive_skips():
    loss = make_loss(obs_dim=3, hidden=(16,))
    updater = TRPOUpdater(loss, critic_epochs=2, critic_minibatch_size=64)
    metrics = updater.update(collect(loss, torch.randn(4, 64, 3), done_every=16))  # Adam state now exists
    assert metrics["train/critic_skipped"] == 0.0 and metrics["train/consecutive_skips"] == 0.0
    critic_params = loss.critic_parameters()
    actor_params = loss.actor_parameters()

    def nan_reward(batch):
        reward = torch.randn(*batch.shape, 1)
        reward[0, 5] = float("nan")  # GAE carries it into value targets and advantages
        return reward

    for skips in (1, 2):
        batch = collect(loss, torch.randn(4, 64, 3), reward_fn=nan_reward, done_every=16)
        critic_before, actor_before = snapshot(critic_params), snapshot(actor_params)
        state_before = optimizer_state_copy(updater.critic_optimizer)

        metrics = updater.update(batch)

        assert not torch.isfinite(batch["value_target"]).all()
        assert metrics["train/critic_skipped"] == 1.0 and metrics["train/step_accepted"] == 0.0
        assert metrics["train/consecutive_skips"] == skips and updater.consecutive_skips == skips
        assert updater.skip_reasons == ["policy step: non-finite policy gradient",
                                        "critic fit: non-finite value target"]
        assert all(math.isfinite(value) for value in metrics.values()), metrics
        assert all_equal(critic_params, critic_before) and all_equal(actor_params, actor_before)
        assert_optimizer_state_equal(updater.critic_optimizer, state_before)

    metrics = updater.update(collect(loss, torch.randn(4, 64, 3), done_every=16))

    assert metrics["train/step_accepted"] == 1.0 and metrics["train/critic_skipped"] == 0.0
    assert metrics["train/consecutive_skips"] == 0.0 and updater.consecutive_skips == 0
    assert updater.skip_reasons == []


@pytest.mark.parametrize("hand_written_backward", [True, False])
def test_critic_fit_that_overflows_is_rolled_back(monkeypatch, hand_written_backward):
    """Finite targets so large that the squared error overflows: caught at the end of the fit."""
    if not hand_written_backward:
        monkeypatch.setattr(PlainMLPRegression, "from_critic", classmethod(lambda cls, m: None))
    loss = make_loss(obs_dim=3, hidden=(16,))
    healthy = collect(loss, torch.randn(200, 3))
    loss.compute_advantage(healthy)
    overflowing = healthy.clone()
    overflowing["value_target"] = torch.full_like(healthy["value_target"], 1e30)
    params = loss.critic_parameters()
    optimizer = make_critic_optimizer(loss)

    before = snapshot(params)  # a fresh optimizer: the state the failed fit created is dropped
    result = fit_critic(loss, overflowing, optimizer, 2, 64)
    assert not result.fitted and "non-finite" in result.skip_reason and result.loss == 0.0
    assert all_equal(params, before) and len(optimizer.state) == 0

    assert fit_critic(loss, healthy, optimizer, 2, 64).fitted
    before, state_before = snapshot(params), optimizer_state_copy(optimizer)
    result = fit_critic(loss, overflowing, optimizer, 2, 64)
    assert not result.fitted
    assert all_equal(params, before)
    assert_optimizer_state_equal(optimizer, state_before)


@pytest.mark.parametrize(
    ("setting", "value"),
    [("max_kl", 0.0), ("max_kl", float("nan")), ("damping", -0.1), ("backtrack_factor", 1.0),
     ("cg_iters", 0), ("max_backtracks", 2.5)],
)
def test_bad_trust_region_settings_raise_naming_the_value(setting, value):
    with pytest.raises(ValueError, match=setting):
        TrustRegion(**{setting: value})
