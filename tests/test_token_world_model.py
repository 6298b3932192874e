"""The world model of grammar robots: link tokens in, per-token state change out; its imagined env."""

import functools
import math

import pytest
import torch
from tensordict import TensorDict
from test_morphology_env import SET
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.collectors import HorizonSchedule, Imagination, ImaginationSettings, StoppingRule, TransitionBuffer
from unipolicy_rl.envs import MorphologyWalkerEnv, RewardWeights, walking_reward
from unipolicy_rl.envs.gait import RandomPhaseGait
from unipolicy_rl.envs.tokens import (
    ACTION_MASK,
    MORPHOLOGY,
    TOKEN_MASK,
    TOKEN_PARENT,
    TOKEN_SIZE,
    TOKENS,
    driven_tokens,
    real_tokens,
)
from unipolicy_rl.token_networks import TokenTransformerSettings, make_token_transformer_actor
from unipolicy_rl.world_models import (
    Dynamics,
    ImaginedEnv,
    ModelTrainer,
    TokenEnsemble,
    TokenLayout,
    make_world_model,
)
from unipolicy_rl.world_models.fresh_error import fresh_error, no_change_error
from unipolicy_rl.world_models.token_ensemble import used_slots

MAX_LINKS = 16  # the largest robot of SET (the thesis robot) has 15 links
LAYOUT = TokenLayout(MAX_LINKS)


@functools.cache
def episodes(seed: int, robots: int = 6, steps: int = 60):
    """Real episodes of the three robots of SET (balanced), as a ``[robots, steps]`` batch."""
    env = MorphologyWalkerEnv(robots, SET, max_links=MAX_LINKS, sampling="balanced")
    env.set_seed(seed)
    batch = env.rollout(steps, RandomPhaseGait(robots, MAX_LINKS, env.control_period, seed=seed),
                        break_when_any_done=False)
    env.close()
    return batch


def buffered(*seeds: int) -> TensorDict:
    buffer = TransitionBuffer(10_000, LAYOUT.from_full, None, LAYOUT.state_key, LAYOUT.build_keys)
    for epoch, seed in enumerate(seeds, start=1):
        buffer.extend(episodes(seed), epoch)
    return buffer.contents()


def small_model(members: int = 3, seed: int = 0) -> TokenEnsemble:
    torch.manual_seed(seed)
    return TokenEnsemble(LAYOUT, MAX_LINKS, members=members, elites=2, embedding=32, hidden=(64,))


@functools.cache
def fitted_model() -> TokenEnsemble:
    model = small_model()
    ModelTrainer(max_epochs=1000, max_steps=400, check_every=50, patience=3).fit(
        model, buffered(0, 1, 3, 4), torch.Generator().manual_seed(0))
    return model


def test_the_tokens_are_the_state_and_imply_their_own_masks():
    batch = episodes(0)
    assert torch.equal(real_tokens(batch[TOKENS]), batch[TOKEN_MASK])
    assert torch.equal(driven_tokens(batch[TOKENS]), batch[ACTION_MASK])
    rows = buffered(0)
    assert rows["state"].shape[-1] == LAYOUT.size == MAX_LINKS * TOKEN_SIZE
    assert torch.equal(LAYOUT.tokens(rows["state"][:3]), batch[TOKENS][0, :3])
    for key in LAYOUT.build_keys:  # what an imagined branch from a buffered state carries
        assert key in rows.keys()
    assert isinstance(small_model(), Dynamics)
    with pytest.raises(ValueError, match=r"tokens must end in \(16, 28\)"):
        LAYOUT.from_full(torch.zeros(2, 12, TOKEN_SIZE))


@pytest.mark.slow  # (a fit of about 13 s)
def test_the_model_fits_held_out_transitions_better_than_predicting_no_change():
    model = fitted_model()
    held_out = buffered(2)  # other episodes of the same robots
    error = fresh_error(model, held_out)["model/fresh_error"]
    baseline = no_change_error(held_out, LAYOUT.robot_size)
    print(f"held-out unexplained share of the state change: model {error:.3f}, no change {baseline:.3f}")
    assert baseline > 0.99
    assert error < 0.9 * baseline


@pytest.mark.slow
def test_a_bfloat16_fit_of_the_token_model_learns_and_keeps_its_weights_in_float32():
    """world_model.trainer.precision=auto fits the grammar's token ensemble in bfloat16 on a CPU that
    computes in it: the token network's ops must run under autocast and still learn (a short fit
    beats predicting no change on held-out episodes, as the float32 fit above does by more)."""
    model = small_model()
    report = ModelTrainer(max_epochs=1000, max_steps=100, check_every=50, patience=3, precision="bfloat16").fit(
        model, buffered(0, 1, 3, 4), torch.Generator().manual_seed(0))
    assert report.extras["fit_bfloat16"] == 1.0
    assert all(p.dtype == torch.float32 for p in model.parameters())
    held_out = buffered(2)
    error = fresh_error(model, held_out)["model/fresh_error"]
    assert math.isfinite(error) and error < 0.95 * no_change_error(held_out, LAYOUT.robot_size)


def test_padding_changes_neither_a_robots_prediction_nor_its_loss():
    model = fitted_model()
    rows = buffered(2)[::15][:24]  # every robot of the batch, in turn
    wide = TokenLayout(MAX_LINKS + 7)
    padded = TokenEnsemble(wide, wide.max_links, members=3, elites=2, embedding=32, hidden=(64,))
    padded.load_state_dict(model.state_dict())  # nothing of the model is tied to the padding
    pad = torch.zeros(24, 7, TOKEN_SIZE)
    state = wide.from_full(torch.cat([LAYOUT.tokens(rows["state"]), pad], 1))
    # The padded slots' actions are garbage (NaN): they drive nothing.
    action = torch.cat([rows["action"], torch.full((24, 7), float("nan"))], 1)
    member = torch.arange(24) % 3
    for deterministic in (True, False):
        torch.manual_seed(0)
        alone = model.predict(rows["state"], rows["action"], rows["design"], member, deterministic)
        torch.manual_seed(0)
        wider = padded.predict(state, action, rows["design"], member, deterministic)
        torch.testing.assert_close(wide.tokens(wider)[:, :MAX_LINKS], LAYOUT.tokens(alone), rtol=1e-5, atol=1e-6)
        assert (wide.tokens(wider)[:, MAX_LINKS:] == 0).all()  # padding stays zeros
    # A robot's loss is its own, beside a larger robot or alone, however far it is padded.
    small = rows[real_tokens(LAYOUT.tokens(rows["state"])).sum(-1) < used_slots(LAYOUT.tokens(rows["state"]))][:1]
    assert len(small) == 1

    def loss(m, state, action, next_state, design):
        x = m.input_norm(m.inputs(state, action, design)).expand(3, -1, -1, -1)
        return m.training_loss(x, m.target_norm(m.targets(state, next_state)).expand(3, -1, -1, -1))

    in_batch = loss(model, rows["state"], rows["action"], rows["next_state"], rows["design"])
    index = int(torch.nonzero((rows["state"] == small["state"]).all(-1))[0])
    own = loss(padded, wide.from_full(torch.cat([LAYOUT.tokens(small["state"]), pad[:1]], 1)),
               torch.cat([small["action"], torch.full((1, 7), float("nan"))], 1),
               wide.from_full(torch.cat([LAYOUT.tokens(small["next_state"]), pad[:1]], 1)), small["design"])
    torch.testing.assert_close(own[:, 0], in_batch[:, index], rtol=1e-5, atol=1e-6)
    assert torch.isfinite(in_batch).all()


def imagined_env(model: TokenEnsemble, batch_size: int = 5) -> tuple[ImaginedEnv, MorphologyWalkerEnv]:
    reference = MorphologyWalkerEnv(1, SET, max_links=MAX_LINKS)
    reference.close()  # only its specs are read
    pool = buffered(0).select("state", "design", *LAYOUT.build_keys)
    env = ImaginedEnv(make_world_model(model, RewardWeights()), reference,
                            lambda n: pool[torch.randint(len(pool), (n,))], batch_size=batch_size)
    return env, reference


def test_the_imagined_env_of_grammar_robots_has_the_real_envs_specs_and_reward():
    model = fitted_model()
    env, reference = imagined_env(model)
    check_env_specs(env)
    real = reference.observation_spec
    for key in (TOKENS, TOKEN_MASK, TOKEN_PARENT, ACTION_MASK, MORPHOLOGY, "design", "physics_fault"):
        assert env.observation_spec[key].shape[1:] == real[key].shape[1:], key
        assert env.observation_spec[key].dtype == real[key].dtype, key
    assert env.action_spec.shape[1:] == reference.action_spec.shape[1:] == (MAX_LINKS,)
    assert env.reward_spec.shape[1:] == reference.reward_spec.shape[1:]
    # A token policy drives it as it drives the real env.
    torch.manual_seed(0)
    actor = make_token_transformer_actor(TOKEN_SIZE, TokenTransformerSettings(d_model=16, feedforward=32, layers=1))
    rollout = env.rollout(6, actor, break_when_any_done=False)
    assert rollout.shape == (5, 6)
    tokens = rollout["next", TOKENS]
    # The reward is the real env's reward of the predicted root token; the build never changes.
    torch.testing.assert_close(rollout["next", "reward"].squeeze(-1), walking_reward(tokens[..., 0, :]))
    for key in LAYOUT.build_keys:
        assert (rollout["next", key] == rollout[key][:, :1]).all(), key
    assert torch.equal(real_tokens(tokens), rollout["next", TOKEN_MASK])
    assert (tokens[~rollout["next", TOKEN_MASK]] == 0).all()
    assert not rollout["next", "terminated"].any()


@pytest.mark.parametrize("stopping", [StoppingRule(kind="fixed", max_updates=2),
                                      StoppingRule(max_updates=2, check_every=1, check_starts=4, check_horizon=3)])
def test_imagination_branches_grammar_robots_from_buffered_states(stopping):
    model = fitted_model()
    reference = MorphologyWalkerEnv(1, SET, max_links=MAX_LINKS)
    reference.close()
    settings = ImaginationSettings(steps_per_batch=20, horizon=HorizonSchedule(start=5, end=5), stopping=stopping)
    imagination = Imagination(model, reference, RewardWeights(), settings, seed=0, episode_length=60)
    torch.manual_seed(0)
    actor = make_token_transformer_actor(TOKEN_SIZE, TokenTransformerSettings(d_model=16, feedforward=32, layers=1))
    data = buffered(0, 1)
    branches = list(imagination.epoch(1, data, actor))
    assert 1 <= len(branches) <= 2
    for branch in branches:
        assert branch.shape == (4, 5) and branch["next", "truncated"][:, -1].all()
        # Every branch starts from a buffered real state, with that state's build.
        first = branch[:, 0]
        match = (first["state"][:, None] == data["state"][None]).all(-1)
        assert match.any(-1).all()
        source = data[match.float().argmax(-1)]
        for key in LAYOUT.build_keys:
            assert torch.equal(first[key], source[key]), key


def test_bad_token_model_settings_name_the_value():
    with pytest.raises(ValueError, match="action_dim must be the env's 16 token slots"):
        TokenEnsemble(LAYOUT, 4)
    with pytest.raises(ValueError, match="embedding must be a positive integer, got 0"):
        TokenEnsemble(LAYOUT, MAX_LINKS, embedding=0)
    with pytest.raises(ValueError, match=r"hidden must be a non-empty list of positive integers .* got \(\)"):
        TokenEnsemble(LAYOUT, MAX_LINKS, hidden=())
    with pytest.raises(ValueError, match="target must be change for TokenEnsemble.* got 'next_state'"):
        TokenEnsemble(LAYOUT, MAX_LINKS, target="next_state")
    with pytest.raises(ValueError, match="max_links must be a positive integer"):
        TokenLayout(0)
