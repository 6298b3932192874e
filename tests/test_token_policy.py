"""The policies that read any body as padded link tokens, and TRPO over their masked actions.

Synthetic tensordicts with the keys of ``unipolicy_rl.envs.tokens`` (no env): a robot is a few
real link tokens with a body tree, padded with empty tokens whose contents are garbage.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from fingerprint import RELATIVE_TOLERANCE, fingerprint
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torch import distributions as D
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.envs.tokens import ACTION_MASK, CLOCK, TOKEN_MASK, TOKEN_PARENT, TOKENS
from unipolicy_rl.masked_normal import MaskedIndependentNormal
from unipolicy_rl.networks import make_actor, make_critic
from unipolicy_rl.objectives import TRPOLoss, TrustRegion, natural_gradient_step
from unipolicy_rl.observation_statistics import ObservationStatistics, refresh_normalizer
from unipolicy_rl.policy import (
    NORMALIZED_TOKENS,
    TOKEN_CRITICS,
    make_actor_critic,
    make_token_actor_critic,
    make_token_norm,
)
from unipolicy_rl.token_networks import (
    TokenEncoder,
    TokenTransformerSettings,
    attention_blocked,
    make_modular_actor,
    make_padded_mlp_actor,
    make_padded_mlp_critic,
    make_pooled_token_critic,
    make_token_transformer_actor,
    make_token_transformer_critic,
    used_slots,
)
from unipolicy_rl.token_statistics import TokenObservationStatistics

CONF = Path(__file__).resolve().parents[1] / "conf"
F = 24  # features per token
SMALL = TokenTransformerSettings(d_model=16, heads=2, layers=2, feedforward=32)
# Two robots of different morphologies: parents per real link (-1: the root).
SNAKE = [-1, 0, 1, 2, 3]          # a chain of 5 links
QUADRUPED = [-1, 0, 0, 0, 0, 1, 2]  # a base with 4 legs, two of them with a second link


@pytest.fixture(autouse=True)
def _single_thread_and_seed():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(threads)


def robots(parents_per_robot: list[list[int]], length: int, batch: int, dtype=torch.float32) -> TensorDict:
    """``batch`` observations of each robot, padded to ``length`` tokens with random garbage.

    The robots alternate along the batch; padding tokens hold random features (a policy must not
    read them) and parent -1; the root's joint is not actuated.
    """
    samples = []
    for index in range(batch):
        parents = parents_per_robot[index % len(parents_per_robot)]
        real = len(parents)
        mask = torch.arange(length) < real
        parent = torch.full((length,), -1, dtype=torch.int64)
        parent[:real] = torch.tensor(parents)
        samples.append(TensorDict({TOKENS: torch.randn(length, F, dtype=dtype), TOKEN_MASK: mask,
                                   TOKEN_PARENT: parent, ACTION_MASK: mask & (parent >= 0)}, batch_size=[]))
    return torch.stack(samples)


def padded(data: TensorDict, length: int) -> TensorDict:
    """``data`` with ``length - L`` more padding slots of garbage on every per-slot entry."""
    extra = length - data[TOKEN_MASK].shape[-1]
    out = data.clone()
    for key, value in data.items():
        if key in (TOKEN_MASK, ACTION_MASK):
            out[key] = torch.cat([value, torch.zeros(*value.shape[:-1], extra, dtype=torch.bool)], -1)
        elif key == TOKEN_PARENT:
            out[key] = torch.cat([value, torch.full((*value.shape[:-1], extra), -1)], -1)
        elif key == TOKENS:
            out[key] = torch.cat([value, 50 * torch.randn(*value.shape[:-2], extra, F, dtype=value.dtype)], -2)
        elif key in ("action", "loc", "scale"):
            garbage = torch.rand(*value.shape[:-1], extra, dtype=value.dtype) + 3
            out[key] = torch.cat([value, garbage], -1)
    return out


def perturbed(module):
    """``module`` with every parameter moved by 0.2 standard normals: a policy away from its
    near-zero initial mean."""
    with torch.no_grad():
        for param in module.parameters():
            param.add_(0.2 * torch.randn_like(param))
    return module


def collect(actor, data: TensorDict) -> TensorDict:
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return actor(data.clone())


def transformer(settings=SMALL, dtype=torch.float32):
    return (make_token_transformer_actor(F, settings, init_log_std=-0.5).to(dtype),
            make_token_transformer_critic(F, settings).to(dtype))


# ------------------------------------------------------------------- padding changes nothing
@pytest.mark.parametrize(("graph_attention", "head"), [
    (False, {}), (True, {}), (False, {"head_hidden": (16, 16), "head_reads_token": True}),
])
def test_padding_leaves_the_transformer_distribution_and_value_unchanged(graph_attention, head):
    settings = TokenTransformerSettings(d_model=16, heads=2, layers=2, feedforward=32, graph_attention=graph_attention,
                                        **head)
    actor, critic = transformer(settings)
    perturbed(actor)
    data = collect(actor, robots([SNAKE, QUADRUPED], length=7, batch=6))
    bigger = padded(data, 12)

    with torch.no_grad():
        small_params, big_params = actor.get_dist_params(data.clone()), actor.get_dist_params(bigger.clone())
        small_dist, big_dist = actor.get_dist(small_params), actor.get_dist(big_params)
        real = data[ACTION_MASK]
        assert small_params["loc"][real].abs().max() > 0.05  # not trivially zero
        torch.testing.assert_close(big_params["loc"][..., :7][real], small_params["loc"][real], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(big_params["scale"][..., :7][real], small_params["scale"][real])
        torch.testing.assert_close(big_dist.log_prob(bigger["action"]), small_dist.log_prob(data["action"]),
                                   atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(big_dist.entropy(), small_dist.entropy())
        torch.testing.assert_close(critic(bigger.clone())["state_value"], critic(data.clone())["state_value"],
                                   atol=1e-5, rtol=1e-5)


def test_padding_leaves_the_modular_policy_unchanged_and_a_reordered_body_acts_the_same():
    actor = perturbed(make_modular_actor(F, (16, 16), init_log_std=-0.5))
    data = collect(actor, robots([SNAKE, QUADRUPED], length=7, batch=6))
    bigger = padded(data, 12)
    with torch.no_grad():
        small, big = actor.get_dist_params(data.clone()), actor.get_dist_params(bigger.clone())
    real = data[ACTION_MASK]
    assert small["loc"][real].abs().max() > 0.05  # not trivially zero
    torch.testing.assert_close(big["loc"][..., :7][real], small["loc"][real], atol=1e-5, rtol=1e-5)

    # The quadruped with its links in another slot order (parents renumbered): each link's joint
    # gets the same mean wherever it sits, as no weight belongs to a slot.
    order = torch.tensor([0, 2, 1, 4, 3, 6, 5])  # new slot -> old slot; each leg's second link still after its hip
    quadruped = data[1:2].clone()
    moved = quadruped.clone()
    old_to_new = torch.argsort(order)
    moved[TOKENS] = quadruped[TOKENS][:, order]
    moved[TOKEN_MASK], moved[ACTION_MASK] = quadruped[TOKEN_MASK][:, order], quadruped[ACTION_MASK][:, order]
    parents = quadruped[TOKEN_PARENT][:, order]
    moved[TOKEN_PARENT] = torch.where(parents >= 0, old_to_new[parents.clamp(min=0)], parents)
    with torch.no_grad():
        loc, moved_loc = actor.get_dist_params(quadruped)["loc"], actor.get_dist_params(moved)["loc"]
    torch.testing.assert_close(moved_loc[:, old_to_new], loc, atol=1e-5, rtol=1e-5)
    # ... where the padded MLP, whose weights belong to slots, acts differently.
    mlp = perturbed(make_padded_mlp_actor(F, 7, (16,), init_log_std=-0.5))
    with torch.no_grad():
        mlp_loc, mlp_moved = mlp.get_dist_params(quadruped)["loc"], mlp.get_dist_params(moved)["loc"]
    assert (mlp_moved[:, old_to_new] - mlp_loc)[quadruped[ACTION_MASK]].abs().max() > 1e-3


def test_the_modular_policy_with_a_clock_reads_it_at_every_joint_and_padding_still_changes_nothing():
    actor = perturbed(make_modular_actor(F, (16, 16), init_log_std=-0.5, clock=True))
    assert CLOCK in actor.in_keys and CLOCK not in make_modular_actor(F, (16, 16)).in_keys
    data = robots([SNAKE, QUADRUPED], length=7, batch=6)
    phase = torch.rand(6, 1) * 2 * torch.pi
    data[CLOCK] = torch.cat([phase.sin(), phase.cos()], -1)
    data = collect(actor, data)
    later = data.clone()
    later[CLOCK] = torch.cat([(phase + 1).sin(), (phase + 1).cos()], -1)
    bigger = padded(data, 12)
    with torch.no_grad():
        now, then, big = (actor.get_dist_params(d.clone())["loc"] for d in (data, later, bigger))
    real = data[ACTION_MASK]
    assert (now - then)[real].abs().min() > 0  # every real joint moves with the phase
    torch.testing.assert_close(big[..., :7][real], now[real], atol=1e-5, rtol=1e-5)
    with pytest.raises(KeyError):  # an env without a clock: the policy says what is missing
        actor(robots([SNAKE], length=7, batch=2))


def test_slot_vectors_let_a_body_move_one_slot_alone_and_padding_still_changes_nothing():
    settings = TokenTransformerSettings(d_model=16, heads=2, layers=2, feedforward=32, slot_embedding=True)
    actor = make_token_transformer_actor(F, settings, init_log_std=-0.5, max_tokens=12)
    encoder = actor.module[0].module.encoder
    assert torch.equal(encoder.slot_embedding, torch.zeros(12, 16))  # starts as the network without slot vectors
    with torch.no_grad():
        for param in actor.parameters():
            param.add_(0.2 * torch.randn_like(param))
    data = collect(actor, robots([SNAKE, QUADRUPED], length=7, batch=6))

    with torch.no_grad():
        loc = actor.get_dist_params(data.clone())["loc"]
        bigger = padded(data, 12)
        big_params = actor.get_dist_params(bigger.clone())
        real = data[ACTION_MASK]
        torch.testing.assert_close(big_params["loc"][..., :7][real], loc[real], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(actor.get_dist(big_params).log_prob(bigger["action"]),
                                   actor.get_dist(actor.get_dist_params(data.clone())).log_prob(data["action"]),
                                   atol=1e-5, rtol=1e-5)
        # Two tokens of the same features act alike without slot vectors, and apart with them.
        twins = data[:1].clone()
        twins[TOKENS][0, 2] = twins[TOKENS][0, 1]
        twins[TOKEN_PARENT][0, 2] = twins[TOKEN_PARENT][0, 1] = 0  # both children of the root
        twin_loc = actor.get_dist_params(twins.clone())["loc"][0]
        assert (twin_loc[1] - twin_loc[2]).abs() > 1e-3
        encoder.slot_embedding.zero_()
        twin_loc = actor.get_dist_params(twins.clone())["loc"][0]
        torch.testing.assert_close(twin_loc[1], twin_loc[2], atol=1e-6, rtol=1e-6)

    with pytest.raises(ValueError, match="12 slots.*13 slots"):
        actor(padded(data, 13))
    with pytest.raises(ValueError, match="max_tokens"):
        make_token_transformer_actor(F, settings)


@pytest.mark.parametrize("graph_attention", [False, True])
def test_the_encoder_cuts_trailing_padding_and_its_real_outputs_stay_exact(graph_attention):
    settings = TokenTransformerSettings(d_model=16, heads=2, layers=2, feedforward=32, graph_attention=graph_attention)
    encoder = TokenEncoder(F, settings)
    data = padded(robots([SNAKE, QUADRUPED], length=7, batch=6), 12)
    tokens, mask, parent = data[TOKENS], data[TOKEN_MASK], data[TOKEN_PARENT]
    assert used_slots(mask) == 7 and used_slots(mask[:1]) == 5 and used_slots(torch.zeros(3, 4, dtype=torch.bool)) == 1

    with torch.no_grad():
        encoded = encoder(tokens, mask, parent)
        # The same layers over all 12 slots, as the encoder ran before it cut the padding.
        blocked = attention_blocked(mask, parent, graph_attention).repeat_interleave(settings.heads, dim=0)
        uncut = encoder.encoder(encoder.embedding(tokens), mask=blocked)
    assert encoded.shape == uncut.shape == (6, 12, 16)
    torch.testing.assert_close(encoded[mask], uncut[mask], atol=1e-6, rtol=1e-6)
    assert torch.equal(encoded[:, 7:], torch.zeros(6, 5, 16))  # slots no robot uses were never computed


def test_padding_leaves_the_pooled_critic_value_unchanged():
    critic = make_pooled_token_critic(F, (16, 16))
    with torch.no_grad():  # away from the initialisation, so the max and the mean both matter
        for param in critic.parameters():
            param.add_(0.2 * torch.randn_like(param))
    data = robots([SNAKE, QUADRUPED], length=7, batch=6)
    bigger = padded(data, 12)
    bigger[TOKENS][..., 9, :] = float("nan")  # not even a non-finite padding row reaches the value

    with torch.no_grad():
        value = critic(data.clone())["state_value"]
        torch.testing.assert_close(critic(bigger.clone())["state_value"], value, atol=1e-5, rtol=1e-5)
    assert value.std() > 1e-3  # the robots' values differ: the test is not comparing constants
    # ... and its gradient stays finite, so a fit on padded data cannot poison the weights.
    critic(bigger.clone())["state_value"].sum().backward()
    assert all(torch.isfinite(param.grad).all() for param in critic.parameters())


def test_the_pooled_critic_values_each_robot_by_its_real_tokens_in_any_order():
    """No slot order is assumed: permuting a robot's real tokens (and its parents with them)
    leaves its value unchanged; changing one real token changes it."""
    critic = make_pooled_token_critic(F, (16, 16))
    data = robots([QUADRUPED], length=9, batch=1)
    order = torch.tensor([3, 0, 6, 1, 5, 2, 4, 7, 8])  # the 7 real tokens shuffled, padding after them
    shuffled = data.clone()
    shuffled[TOKENS], shuffled[TOKEN_MASK] = data[TOKENS][:, order], data[TOKEN_MASK][:, order]
    moved = data.clone()
    moved[TOKENS][:, 4] += 1.0
    with torch.no_grad():
        value = critic(data.clone())["state_value"]
        torch.testing.assert_close(critic(shuffled)["state_value"], value, atol=1e-6, rtol=1e-6)
        assert (critic(moved)["state_value"] - value).abs().item() > 1e-4


def trpo_batch(loss: TRPOLoss, data: TensorDict) -> TensorDict:
    batch = collect(loss.actor_network, data)
    batch["advantage"] = torch.randn(batch.shape[0], 1, dtype=batch["loc"].dtype)
    return batch


def test_padding_leaves_the_trpo_step_unchanged():
    actor, critic = transformer(dtype=torch.float64)
    twin_actor, twin_critic = transformer(dtype=torch.float64)
    twin_actor.load_state_dict(actor.state_dict())
    twin_critic.load_state_dict(critic.state_dict())
    loss, twin = TRPOLoss(actor, critic), TRPOLoss(twin_actor, twin_critic)
    batch = trpo_batch(loss, robots([SNAKE, QUADRUPED], length=7, batch=64, dtype=torch.float64))
    bigger = padded(batch, 11)
    trust_region = TrustRegion(max_kl=0.01)

    result = natural_gradient_step(loss, batch, trust_region=trust_region)
    twin_result = natural_gradient_step(twin, bigger, trust_region=trust_region)

    assert result.accepted and twin_result.accepted
    assert twin_result.kl == pytest.approx(result.kl, rel=1e-6)
    assert twin_result.step_size == pytest.approx(result.step_size, rel=1e-6)
    moved = False
    for param, twin_param, start in zip(loss.actor_parameters(), twin.actor_parameters(),
                                        TRPOLoss(*transformer(dtype=torch.float64)).actor_parameters(), strict=True):
        torch.testing.assert_close(twin_param, param, atol=1e-9, rtol=1e-7)
        moved |= not torch.equal(param, start)
    assert moved


# ----------------------------------------------------------------------- masked slots
def test_masked_slots_count_for_nothing_in_log_prob_entropy_and_kl():
    loc, scale = torch.randn(5, 6), torch.rand(5, 6) + 0.5
    other_loc, other_scale = torch.randn(5, 6), torch.rand(5, 6) + 0.5
    mask = torch.rand(5, 6) > 0.4
    mask[:, 0] = True
    action = torch.randn(5, 6)

    def scrambled(tensor):  # new values on the masked-out slots only
        return torch.where(mask, tensor, torch.randn_like(tensor) * 100)

    p, q = MaskedIndependentNormal(loc, scale, mask), MaskedIndependentNormal(other_loc, other_scale, mask)
    p2, q2 = (MaskedIndependentNormal(scrambled(loc), scrambled(scale).abs(), mask),
              MaskedIndependentNormal(scrambled(other_loc), scrambled(other_scale).abs(), mask))

    normal, other = D.Normal(loc, scale), D.Normal(other_loc, other_scale)
    expected_log_prob = (normal.log_prob(action) * mask).sum(-1)
    torch.testing.assert_close(p.log_prob(action), expected_log_prob)
    torch.testing.assert_close(p2.log_prob(scrambled(action)), expected_log_prob)
    torch.testing.assert_close(p2.entropy(), (normal.entropy() * mask).sum(-1))
    torch.testing.assert_close(D.kl_divergence(p2, q2), (D.kl_divergence(normal, other) * mask).sum(-1))
    assert p.log_prob(action).shape == p.entropy().shape == D.kl_divergence(p, q).shape == (5,)
    # A non-finite value in a masked slot (an action the env never applied) stays out, gradient included.
    poisoned = torch.where(mask, action, torch.tensor(float("nan")))
    loc.requires_grad_(True)
    log_prob = MaskedIndependentNormal(loc, scale, mask).log_prob(poisoned)
    (gradient,) = torch.autograd.grad(log_prob.sum(), loc)
    assert torch.isfinite(log_prob).all() and torch.isfinite(gradient).all()
    assert (gradient[~mask] == 0).all()
    sample = p.sample()
    assert (sample[~mask] == 0).all() and (p.mode[~mask] == 0).all()
    with pytest.raises(ValueError, match="different action masks"):
        D.kl_divergence(p, MaskedIndependentNormal(loc, scale, ~mask))


# ----------------------------------------------------------------------- graph attention
def output_change(actor, data, token: int) -> torch.Tensor:
    """Per-slot change of the mean when one token's features change."""
    with torch.no_grad():
        before = actor.get_dist_params(data.clone())["loc"]
        moved = data.clone()
        moved[TOKENS][:, token] += 5 * torch.randn(F)
        return (actor.get_dist_params(moved)["loc"] - before).abs()[0]


def test_graph_attention_sees_only_parent_children_and_itself():
    settings = TokenTransformerSettings(d_model=16, heads=2, layers=1, feedforward=32, graph_attention=True)
    actor = make_token_transformer_actor(F, settings)
    with torch.no_grad():
        for param in actor.parameters():
            param.add_(0.2 * torch.randn_like(param))
    data = robots([QUADRUPED], length=9, batch=1)
    # QUADRUPED: 0 the base; 1-4 its children; 5 the child of 1, 6 the child of 2; 7, 8 padding.
    neighbours = {0: {0, 1, 2, 3, 4}, 1: {0, 1, 5}, 5: {1, 5}, 3: {0, 3}}
    for token, expected in neighbours.items():
        changed = {slot for slot, change in enumerate(output_change(actor, data, token).tolist()) if change > 1e-6}
        assert changed == expected, (token, changed)
    # Padding is seen by no one; with full attention every real token sees every real token.
    assert (output_change(actor, data, 8)[:7] == 0).all()
    full = make_token_transformer_actor(F, TokenTransformerSettings(d_model=16, heads=2, layers=1, feedforward=32))
    full.load_state_dict(actor.state_dict())
    assert (output_change(full, data, 5)[:7] > 1e-6).all()


# ------------------------------------------------------------------------- TRPO on tokens
@pytest.mark.parametrize("architecture", ["token_transformer", "token_transformer_slots", "token_mlp",
                                          "token_modular"])
def test_trpo_step_on_token_data_respects_the_kl_bound(architecture):
    if architecture == "token_transformer":
        actor, critic = transformer()
    elif architecture == "token_transformer_slots":  # the slot vectors in the step (zero at first, moved by it)
        settings = TokenTransformerSettings(d_model=16, heads=2, layers=2, feedforward=32, slot_embedding=True)
        actor = make_token_transformer_actor(F, settings, -0.5, max_tokens=8)
        critic = make_pooled_token_critic(F, (16,))
    elif architecture == "token_modular":
        actor, critic = make_modular_actor(F, (32, 32), init_log_std=-0.5), make_pooled_token_critic(F, (32,))
    else:
        actor, critic = make_padded_mlp_actor(F, 8, (32,), init_log_std=-0.5), make_padded_mlp_critic(F, 8, (32,))
    loss = TRPOLoss(actor, critic)
    batch = trpo_batch(loss, robots([SNAKE, QUADRUPED], length=8, batch=128))
    batch["value_target"] = torch.randn(128, 1)
    before = loss(batch)
    assert before["kl"].abs() < 1e-6
    max_kl = 0.01

    result = natural_gradient_step(loss, batch, trust_region=TrustRegion(max_kl=max_kl))

    after = loss(batch)
    assert result.accepted, result.skip_reason
    assert 0 < after["kl"] <= max_kl
    assert after["kl"].item() == pytest.approx(result.kl, rel=1e-4)
    assert before["loss_objective"] - after["loss_objective"] > 0
    predicted_kl = max_kl * 0.8 ** (2 * (result.line_search_tries - 1))  # the Fisher model sized the step
    assert 0.4 * predicted_kl < result.kl <= 1.5 * predicted_kl
    if architecture == "token_transformer_slots":
        assert actor.module[0].module.encoder.slot_embedding.abs().max() > 0


# Recorded on main (torch 2.13 CPU, one thread, AVX-512; the step was first recorded as bits before
# the masked-action changes, commit afd0a0f): the flat policy's TRPO step on the case of
# test_trpo.py's accepted-step test, as its KL, its step size and the actor's fingerprint
# (tests/fingerprint.py).
FLAT_STEP = [0.007853932678699493, 0.973816482385167, 89.4897429684188, 40.053716265450404]


def test_flat_trpo_step_is_what_it_was_before_masked_actions():
    loss = TRPOLoss(make_actor(4, 2, (16, 16)), make_critic(4, (16, 16)))
    batch = TensorDict(observation=torch.randn(8, 64, 4), batch_size=[8, 64])
    batch = collect(loss.actor_network, batch)
    done = torch.zeros(8, 64, 1, dtype=torch.bool)
    done[:, 15::16] = True
    batch["next"] = TensorDict(observation=torch.randn(8, 64, 4), reward=torch.randn(8, 64, 1), done=done,
                               terminated=done.clone(), batch_size=[8, 64])
    loss.compute_advantage(batch)

    result = natural_gradient_step(loss, batch.reshape(-1), trust_region=TrustRegion(max_kl=0.01))

    numbers = [float(result.kl), float(result.step_size), *fingerprint(list(loss.actor_parameters()))]
    if not torch.__version__.startswith("2.13"):
        pytest.skip(f"the recorded numbers are torch 2.13's; this is {torch.__version__}")
    assert numbers == pytest.approx(FLAT_STEP, rel=RELATIVE_TOLERANCE)


@pytest.mark.parametrize("fraction", [1.0, 0.2])
def test_the_fisher_product_on_a_subsample_keeps_the_step_within_its_kl_bound(fraction):
    """``fisher_fraction`` sizes the step from every fifth sample's Fisher products; the line search
    checks the whole batch's KL, so the accepted step stays within the bound. At 1.0 the step is
    exactly the default's."""
    actor, critic = transformer()
    loss = TRPOLoss(actor, critic)
    batch = trpo_batch(loss, robots([SNAKE, QUADRUPED], length=8, batch=200))
    start = [param.detach().clone() for param in loss.actor_parameters()]
    max_kl = 0.01

    default = natural_gradient_step(loss, batch, trust_region=TrustRegion(max_kl=max_kl))
    default_params = [param.detach().clone() for param in loss.actor_parameters()]
    with torch.no_grad():
        for param, value in zip(loss.actor_parameters(), start, strict=True):
            param.copy_(value)
    result = natural_gradient_step(loss, batch, trust_region=TrustRegion(max_kl=max_kl, fisher_fraction=fraction))

    assert result.accepted, result.skip_reason
    with torch.no_grad():  # the whole batch's KL, computed afresh
        kl = loss.mean_kl(loss.behaviour_distribution(batch), loss.policy_distribution(batch)).item()
    assert 0 < kl <= max_kl and kl == pytest.approx(result.kl, rel=1e-4)
    moved = [torch.equal(a, b) for a, b in zip(loss.actor_parameters(), default_params, strict=True)]
    if fraction == 1.0:
        assert all(moved) and result == default  # bit for bit the default step
    else:
        assert not all(moved)  # the subsample's curvature gave another step


def test_fisher_subsample_takes_evenly_spaced_samples():
    from unipolicy_rl.objectives import fisher_subsample

    assert fisher_subsample(1000, 1.0) is None and fisher_subsample(3, 0.99) is None
    assert fisher_subsample(1000, 0.2).tolist() == list(range(0, 1000, 5))  # OpenAI baselines' arr[::5]
    assert fisher_subsample(7, 0.2).tolist() == [0, 3]
    assert fisher_subsample(1, 0.01) is None
    for bad in (0, -0.5, 1.5, float("nan"), True):
        with pytest.raises(ValueError, match="fisher_fraction must lie in"):
            TrustRegion(fisher_fraction=bad)


def test_the_trpo_learner_refreshes_token_statistics_over_real_tokens_with_the_masks():
    from unipolicy_rl.factories import make_learner

    cfg = policy_config("token_transformer", "robot=grammar", "policy.network.d_model=16",
                        "policy.network.feedforward=32")
    learner = make_learner(cfg, F, 9)
    assert {TOKENS, TOKEN_MASK, TOKEN_PARENT, ACTION_MASK, ("next", TOKENS), ("next", TOKEN_MASK)} <= \
        set(learner.batch_keys)
    assert "observation" not in learner.batch_keys
    data = robots([SNAKE, QUADRUPED], length=9, batch=12)
    data[TOKENS] = 3 + 2 * data[TOKENS]
    batch = data.reshape(3, 4)
    metrics = learner.refresh_observation_normalizer(batch)

    reference = ObservationStatistics(F)
    reference.update(data[TOKENS][data[TOKEN_MASK]])
    assert learner.statistics.count == int(data[TOKEN_MASK].sum())  # padding is no observation
    torch.testing.assert_close(learner.normalizer.loc, reference.loc)
    assert abs(metrics["train/refresh_kl"]) < 1e-6  # preserve: the policy did not move


# ------------------------------------------------------------------------------ critics
@pytest.mark.parametrize("critic_kind", TOKEN_CRITICS)
def test_the_critic_fit_lowers_the_value_loss_of_every_token_critic(critic_kind):
    from unipolicy_rl.objectives import fit_critic, make_critic_optimizer

    cfg = policy_config("token_transformer", f"policy.critic={critic_kind}", "policy.network.d_model=16",
                        "policy.network.feedforward=32", "algo.critic_hidden=[32,32]")
    actor, critic = make_token_actor_critic(cfg, F, 8)
    loss = TRPOLoss(actor, critic)
    data = make_token_norm(F)(robots([SNAKE, QUADRUPED], length=8, batch=256))
    # A value the tokens determine: the mean of a real-token feature, offset by the robot's size.
    real = data[TOKEN_MASK].unsqueeze(-1).float()
    data["value_target"] = ((data[TOKENS][..., :1] * real).sum(-2) / real.sum(-2) + real.sum(-2) / 4).detach()

    def value_loss() -> float:
        with torch.no_grad():
            return loss.critic_loss(data.clone()).item()

    before = value_loss()
    result = fit_critic(loss, data, make_critic_optimizer(loss, 1e-3), epochs=10, minibatch_size=64,
                        generator=torch.Generator().manual_seed(0))

    assert result.fitted, result.skip_reason
    assert value_loss() < 0.5 * before


@pytest.mark.parametrize("critic_kind", TOKEN_CRITICS)
def test_gae_runs_every_token_critic_on_states_and_next_states(critic_kind):
    """The value estimator reads each critic on a batch's states and next states: the values it
    writes are the critic's own (the transformer's cut of unused padding has a shape that depends
    on the batch, which vmap cannot trace)."""
    cfg = policy_config("token_transformer", f"policy.critic={critic_kind}", "policy.network.d_model=16",
                        "policy.network.feedforward=32", "algo.critic_hidden=[32,32]")
    actor, critic = make_token_actor_critic(cfg, F, 8)
    loss = TRPOLoss(actor, critic)
    loss.make_value_estimator(gamma=0.99, lmbda=0.95)
    normalise = make_token_norm(F)
    batch = collect(actor, normalise(robots([SNAKE, QUADRUPED], length=8, batch=20))).reshape(2, 10)
    following = normalise(robots([SNAKE, QUADRUPED], length=8, batch=20)).reshape(2, 10)
    batch["next"] = following.update({"reward": torch.randn(2, 10, 1), "done": torch.zeros(2, 10, 1, dtype=torch.bool),
                                      "terminated": torch.zeros(2, 10, 1, dtype=torch.bool)})
    loss.compute_advantage(batch)
    with torch.no_grad():
        own = critic(batch.exclude("state_value", "next").clone())["state_value"]
        own_next = critic(following.exclude("state_value").clone())["state_value"]
    torch.testing.assert_close(batch["state_value"], own)
    torch.testing.assert_close(batch["next", "state_value"], own_next)
    assert torch.isfinite(batch["advantage"]).all()


def test_the_default_token_transformer_critic_and_each_choice_build_as_named():
    from unipolicy_rl.token_networks import PooledTokenCritic, _TransformerCriticNetwork

    data = robots([SNAKE, QUADRUPED], length=7, batch=4)
    kinds = {"transformer": _TransformerCriticNetwork, "pooled": PooledTokenCritic,
             "padded_mlp": make_padded_mlp_critic(F, 7).module.__class__}
    for kind, network in kinds.items():
        _, critic = make_token_actor_critic(policy_config("token_transformer", f"policy.critic={kind}"), F, 7)
        assert isinstance(critic.module, network), kind
        with torch.no_grad():
            assert critic(make_token_norm(F)(data.clone()))["state_value"].shape == (4, 1)
    _, default = make_token_actor_critic(policy_config("token_transformer"), F, 7)
    assert isinstance(default.module, PooledTokenCritic)  # measured as good and cheaper (docs/grammar.md)
    small = ("policy.critic=transformer", "policy.critic_network={_target_:unipolicy_rl.token_networks."
             "TokenTransformerSettings,d_model:16,heads:2,layers:1,feedforward:32}")
    _, critic = make_token_actor_critic(policy_config("token_transformer", *small), F, 7)
    assert critic.module.encoder.settings == TokenTransformerSettings(d_model=16, heads=2, layers=1, feedforward=32)
    _, critic = make_token_actor_critic(policy_config("token_mlp", "policy.critic=pooled"), F, 7)
    assert isinstance(critic.module, PooledTokenCritic)


@pytest.mark.parametrize(("policy", "overrides", "message"), [
    ("token_transformer", ["policy.critic=attention"],
     r"policy.critic must be one of \('transformer', 'pooled', 'padded_mlp'\), got 'attention'"),
    ("token_mlp", ["policy.critic=transformer"],
     "policy.critic=transformer takes its sizes from policy.critic_network or policy.network, and "
     "policy=token_mlp has neither"),
])
def test_a_bad_critic_is_refused_by_name_by_the_factory(policy, overrides, message):
    """The same check as validation's at start-up (tests/test_validation.py), for a caller that skips it."""
    with pytest.raises(ValueError, match=message):
        make_token_actor_critic(policy_config(policy, *overrides), F, 7)


def test_a_token_policy_saved_before_the_critic_setting_resumes_with_the_critic_it_had():
    from omegaconf import OmegaConf

    from unipolicy_rl.resume import settings_for_resume

    for policy, critic in (("token_transformer", "transformer"), ("token_mlp", "padded_mlp")):
        today = policy_config(policy, "robot=grammar", "policy.critic=pooled")
        saved = OmegaConf.to_container(today, resolve=False)
        del saved["policy"]["critic"]  # the config as a run saved it before policy.critic existed
        saved["policy"].pop("critic_network", None)
        resumed = settings_for_resume(today, {"config": saved}, named=[], choices={}, path="old.pt")
        assert resumed.policy.critic == critic
        _, built = make_token_actor_critic(resumed, F, 7)
        _, expected = make_token_actor_critic(policy_config(policy, f"policy.critic={critic}"), F, 7)
        assert type(built.module) is type(expected.module)


# -------------------------------------------------------------------------- statistics
def test_token_statistics_and_normaliser_ignore_padding():
    data = robots([SNAKE, QUADRUPED], length=7, batch=10)
    data[TOKENS] = 3 + 2 * data[TOKENS]
    statistics, padded_statistics = TokenObservationStatistics(F), TokenObservationStatistics(F)
    statistics.update(data[TOKENS], data[TOKEN_MASK])
    bigger = padded(data, 12)
    padded_statistics.update(bigger[TOKENS][:4], bigger[TOKEN_MASK][:4])  # two epochs merge exactly
    padded_statistics.update(bigger[TOKENS][4:], bigger[TOKEN_MASK][4:])

    reference = ObservationStatistics(F)
    reference.update(data[TOKENS][data[TOKEN_MASK]])
    assert padded_statistics.count == statistics.count == int(data[TOKEN_MASK].sum())
    torch.testing.assert_close(padded_statistics.loc, reference.loc)
    torch.testing.assert_close(padded_statistics.scale, reference.scale)
    torch.testing.assert_close(statistics.scale, reference.scale)

    normalizer = make_token_norm(F)
    padded_statistics.copy_to(normalizer)
    out = normalizer(bigger.clone())[NORMALIZED_TOKENS]
    real = bigger[TOKEN_MASK]
    assert (out[~real] == 0).all()
    torch.testing.assert_close(out[real], (bigger[TOKENS][real] - reference.loc) / reference.scale)
    with pytest.raises(ValueError, match="token_mask"):
        statistics.update(data[TOKENS], data[TOKEN_MASK].float())


@pytest.mark.parametrize(("architecture", "critic", "overrides"), [
    ("token_transformer", "transformer", []), ("token_transformer", "pooled", []), ("token_mlp", "padded_mlp", []),
    ("token_transformer", "pooled", ["policy.network.head_hidden=[8]", "policy.network.head_reads_token=true"]),
    ("token_transformer", "pooled", ["policy.network.head_reads_token=true"]),
    ("token_modular", "pooled", []),
])
def test_a_preserving_refresh_leaves_token_networks_unchanged(architecture, critic, overrides):
    cfg = policy_config(architecture, f"policy.critic={critic}", *overrides)
    actor, critic = make_token_actor_critic(cfg, F, 7)
    normalizer = make_token_norm(F)
    with torch.no_grad():
        for param in [*actor.parameters(), *critic.parameters()]:
            param.add_(0.2 * torch.randn_like(param))
    data = robots([SNAKE, QUADRUPED], length=7, batch=16)
    data[TOKENS] = 3 + 2 * data[TOKENS]

    def outputs():
        with torch.no_grad():
            normalised = normalizer(data.clone())
            loc = actor.get_dist_params(normalised.clone())["loc"][data[ACTION_MASK]]
            return loc, critic(normalised)["state_value"]

    loc_before, value_before = outputs()
    statistics = TokenObservationStatistics(F)
    statistics.update(data[TOKENS], data[TOKEN_MASK])
    refresh_normalizer(statistics, normalizer, (actor, critic), "preserve")
    loc_after, value_after = outputs()

    assert not torch.equal(normalizer.loc, torch.zeros(F))
    torch.testing.assert_close(loc_after, loc_before, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(value_after, value_before, atol=1e-4, rtol=1e-4)


# ---------------------------------------------------------------------- config and settings
def policy_config(name: str, *overrides: str):
    with initialize_config_dir(str(CONF), version_base=None):
        return compose("config", overrides=[f"policy={name}", *overrides])


def test_policy_group_composes_and_builds_each_architecture():
    default = policy_config("mlp")
    with initialize_config_dir(str(CONF), version_base=None):
        assert compose("config").policy.name == "mlp"  # the default: today's flat MLP, built as before
    actor, _ = make_actor_critic(default, 18, 4)
    assert [m.out_features for m in actor.modules() if isinstance(m, torch.nn.Linear)] == [64, 64, 4]
    with pytest.raises(ValueError, match="token_transformer"):
        make_actor_critic(policy_config("token_transformer"), 18, 4)

    data = robots([SNAKE, QUADRUPED], length=7, batch=4)
    for name, overrides in [("token_transformer", ["policy.network.graph_attention=true"]),
                            ("token_transformer", ["policy.network.slot_embedding=true", "policy.critic=transformer"]),
                            ("token_mlp", []), ("token_modular", [])]:
        cfg = policy_config(name, *overrides)
        actor, critic = make_token_actor_critic(cfg, F, 7)
        with torch.no_grad():
            out = critic(actor(make_token_norm(F)(data.clone())))
        assert out["action"].shape == (4, 7) and out["state_value"].shape == (4, 1)
        assert (out["action"][~data[ACTION_MASK]] == 0).all()
        assert out["scale"].min().item() == pytest.approx(torch.tensor(cfg.algo.init_log_std).exp().item())
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):  # evaluation: the mean
            evaluated = actor(make_token_norm(F)(data.clone()))
        real = data[ACTION_MASK]
        assert torch.equal(evaluated["action"][real], evaluated["loc"][real])
        assert (evaluated["action"][~real] == 0).all()


@pytest.mark.parametrize(("setting", "value"), [
    ("d_model", 30), ("heads", 0), ("layers", 0), ("feedforward", -1), ("activation", "tanh"),
    ("graph_attention", "yes"), ("layers", 2.5), ("slot_embedding", 1), ("head_hidden", [0]),
    ("head_reads_token", "no"),
])
def test_bad_transformer_settings_raise_naming_the_value(setting, value):
    settings = {"d_model": 32, "heads": 4}
    with pytest.raises(ValueError, match=rf"{setting}.*{value}|{value}.*{setting}" if setting != "d_model"
                       else r"d_model=30 must be divisible by heads=4"):
        TokenTransformerSettings(**{**settings, setting: value})


def test_bad_token_inputs_raise_naming_the_problem():
    with pytest.raises(ValueError, match="token_features"):
        make_token_transformer_actor(0)
    actor = make_padded_mlp_actor(F, 7)
    with pytest.raises(ValueError, match="7 tokens of 24 features"):
        actor(robots([SNAKE], length=9, batch=2))
    with pytest.raises(ValueError, match="action mask"):
        MaskedIndependentNormal(torch.zeros(2, 3), torch.ones(2, 3), None)
    with pytest.raises(ValueError, match="policy.name"):
        make_token_actor_critic(policy_config("mlp", "policy.name=snake"), F, 7)
