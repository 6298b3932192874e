"""MorphologyWalkerEnv: robots of different grammar morphologies in one batch, as padded link tokens."""

from pathlib import Path

import pybullet
import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.env_factories import env_kwargs, make_morphology_env
from unipolicy_rl.envs import BatchedWalkerEnv, DesignDistribution, MorphologyWalkerEnv, PhysicsSettings, walking_reward
from unipolicy_rl.envs.reward import BASE_X, BASE_X_DOT, BASE_Y, BASE_Z
from unipolicy_rl.envs.slot_layout import StructuralLayout
from unipolicy_rl.envs.tokens import (
    ACTION_MASK,
    CLOCK,
    FEATURE_INDEX,
    MORPHOLOGY,
    TOKEN_FEATURES,
    TOKEN_MASK,
    TOKEN_PARENT,
    TOKEN_SIZE,
    TOKENS,
)
from unipolicy_rl.robots.grammar import LINK_KINDS, VERTEBRATE, LimbLink, Morphology, describe
from unipolicy_rl.robots.grammar.split import HELD_OUT_LIMITS

# Two small robots beside the thesis robot (15 links, 10 hinges): 10 links (a lift body joint and
# one-link legs, 5 hinges) and 6 links (a fixed body joint, one leg pair, 2 hinges).
TEN_LINKS = Morphology(((LimbLink("make_obtuse_lift_limb_joint", "make_normal_limb_link"),),
                        (LimbLink("make_acute_lift_limb_joint", "make_long_limb_link"),)), ("make_lift_body_joint",))
SIX_LINKS = Morphology(((LimbLink("make_obtuse_lift_limb_joint", "make_long_limb_link"),), ()),
                        ("make_fixed_body_joint",))
SET = (VERTEBRATE, TEN_LINKS, SIX_LINKS)
CONF = Path(__file__).resolve().parents[1] / "conf"
DE = DesignDistribution.fixed(0.175, 0.5)


def _env(num_robots=3, morphologies=SET, **kwargs) -> MorphologyWalkerEnv:
    return MorphologyWalkerEnv(num_robots, morphologies, **kwargs)


def _forced(env, morphologies, designs=None) -> TensorDict:
    """A reset tensordict forcing each robot's morphology (and design)."""
    n = env.batch_size[0]
    td = TensorDict({MORPHOLOGY: torch.tensor(morphologies).reshape(n, 1)}, batch_size=[n])
    if designs is not None:
        td["design"] = torch.tensor(designs, dtype=torch.float32)
    return env.reset(td)


def test_check_env_specs_passes_and_specs_describe_the_padding():
    env = _env(max_links=20)
    check_env_specs(env, seed=0)
    spec = env.observation_spec
    assert spec[TOKENS].shape == (3, 20, TOKEN_SIZE)
    for key in (TOKEN_MASK, TOKEN_PARENT, ACTION_MASK):
        assert spec[key].shape == (3, 20)
    assert spec[TOKEN_MASK].dtype == spec[ACTION_MASK].dtype == torch.bool
    assert spec[TOKEN_PARENT].dtype == torch.int64 and spec[MORPHOLOGY].shape == (3, 1)
    assert env.action_spec.shape == (3, 20)
    assert env.action_spec.space.low.min() == -1 and env.action_spec.space.high.max() == 1
    env.close()


def test_token_layout_starts_with_the_rewards_base_numbers():
    assert TOKEN_SIZE == len(TOKEN_FEATURES) == len(set(TOKEN_FEATURES))
    assert [FEATURE_INDEX[name] for name in ("x", "y", "z", "vx")] == [BASE_X, BASE_Y, BASE_Z, BASE_X_DOT]
    assert [name for name in TOKEN_FEATURES if name.startswith("kind_")] == [f"kind_{kind}" for kind in LINK_KINDS]


def test_masks_and_parents_match_each_robots_links_and_actuated_joints():
    env = _env(max_links=16)
    td = _forced(env, [0, 1, 2])
    for i, morphology in enumerate(SET):
        robot = describe(morphology.derivation())  # every hinge driven, as the env by default
        n = len(robot.links)
        assert td[TOKEN_MASK][i].tolist() == [True] * n + [False] * (16 - n)
        parent_of = {robot.link_index(joint.child): robot.link_index(joint.parent) for joint in robot.joints}
        parents = [parent_of.get(index, -1) for index in range(n)]
        assert td[TOKEN_PARENT][i].tolist() == parents + [-1] * (16 - n)
        driven = {robot.link_index(joint.child) for joint in robot.actuated_joints}
        assert torch.nonzero(td[ACTION_MASK][i]).flatten().tolist() == sorted(driven)
        assert len(driven) == len(robot.hinges) == {0: 10, 1: 5, 2: 2}[i]
        actuated = td[TOKENS][i, :, FEATURE_INDEX["actuated"]]
        assert torch.equal(actuated.bool(), td[ACTION_MASK][i])
    env.close()


def test_padding_slots_are_exactly_zero_and_masked_through_steps():
    env = _env(max_links=18)
    env.set_seed(0)
    td = _forced(env, [2, 1, 0])
    for _ in range(4):
        padding = ~td[TOKEN_MASK]
        assert padding.sum() == (18 - 6) + (18 - 10) + (18 - 15)
        assert torch.equal(td[TOKENS][padding], torch.zeros(int(padding.sum()), TOKEN_SIZE))
        assert (td[TOKEN_PARENT][padding] == -1).all() and not td[ACTION_MASK][padding].any()
        assert (td[TOKENS][~padding].abs().sum(-1) > 0).all()  # every real token says something (its kind)
        td = env.step(td.set("action", torch.rand(3, 18) * 2 - 1))["next"]
    env.close()


def test_the_structural_layout_moves_each_link_to_its_roles_slot_and_nothing_else():
    """The same robots, seed and actions in both layouts: the structural tokens are the packed
    ones moved to their slots (parents, masks and motors following), padding zero in the gaps;
    and a leg pair's links sit at the same slots on robots with different numbers of segments."""
    layout = StructuralLayout(body_slots=3, leg_slots=3)  # SET: at most 3 segments, 2 pairs, 1-2 leg links
    packed, structural = _env(max_links=15), _env(token_layout=layout)
    assert structural.max_links == 3 + 2 * 2 * 3
    slots = [describe(m.derivation()).links for m in SET]
    slots = [torch.as_tensor(layout.slots([link.name for link in links])) for links in slots]
    assert slots[0][:4].tolist() == [0, 1, 2, 3] and slots[1][:3].tolist() == [0, 1, 3]  # first pair's mount at 3
    actions = torch.rand(5, 3, 15, generator=torch.Generator().manual_seed(2)) * 2 - 1
    tds = []
    for env in (packed, structural):
        env.set_seed(0)
        td, steps = _forced(env, [0, 1, 2]), []
        for action in actions:
            moved = torch.zeros(3, env.max_links)
            for i, s in enumerate(slots):
                moved[i, s if env is structural else torch.arange(len(s))] = action[i, :len(s)]
            td = env.step(td.set("action", moved))["next"]
            steps.append(td.clone())
        tds.append(torch.stack(steps))
    for i, s in enumerate(slots):
        n = len(s)
        assert torch.equal(tds[1][:, i][TOKENS][:, s], tds[0][:, i][TOKENS][:, :n])
        assert torch.equal(tds[1][:, i][ACTION_MASK][:, s], tds[0][:, i][ACTION_MASK][:, :n])
        parents = tds[0][0, i][TOKEN_PARENT][:n]
        assert torch.equal(tds[1][0, i][TOKEN_PARENT][s], torch.where(parents >= 0, s[parents.clamp(min=0)], -1))
        gaps = torch.ones(structural.max_links, dtype=torch.bool)
        gaps[s] = False
        assert tds[1][:, i][TOKEN_MASK][:, s].all() and not tds[1][:, i][TOKEN_MASK][:, gaps].any()
        assert (tds[1][:, i][TOKENS][:, gaps] == 0).all() and (tds[1][0, i][TOKEN_PARENT][gaps] == -1).all()
    assert torch.equal(tds[1]["reward"], tds[0]["reward"])
    check_env_specs(structural, seed=0)
    packed.close()
    structural.close()


def test_reset_forces_morphology_and_design_and_rebuilds_only_masked_robots():
    env = _env(2)
    env.set_seed(0)
    td = _forced(env, [0, 2], [[0.16, 0.55], [0.19, 0.45]])
    assert td[TOKEN_MASK].sum(-1).tolist() == [15, 6]
    assert td[MORPHOLOGY].flatten().tolist() == [0, 2]
    torch.testing.assert_close(td["design"], torch.tensor([[0.16, 0.55], [0.19, 0.45]]))
    for _ in range(3):
        td = env.step(td.set("action", torch.full((2, 15), 0.5)))["next"]
    before = td.clone()
    td.update({"_reset": torch.tensor([[False], [True]]), MORPHOLOGY: torch.tensor([[0], [1]])})
    after = env.reset(td)
    assert after[TOKEN_MASK].sum(-1).tolist() == [15, 10]  # a new body, a new link count
    assert after[MORPHOLOGY].flatten().tolist() == [0, 1]
    assert torch.equal(after[TOKENS][0], before[TOKENS][0])
    assert after[TOKENS][1, 0, FEATURE_INDEX["x"]] == 0  # back at the start
    assert env._steps.tolist() == [3, 0]
    env.close()


def test_the_clock_is_each_robots_phase_since_its_episode_began():
    env = _env(2, clock_frequency=1.5)
    check_env_specs(env, seed=0)
    assert CLOCK not in _env(1).observation_spec.keys()  # no clock unless asked for
    td = _forced(env, [0, 2])
    torch.testing.assert_close(td[CLOCK], torch.tensor([[0.0, 1.0], [0.0, 1.0]]))  # phase 0 at the start
    for _ in range(4):
        td = env.step(td.set("action", torch.zeros(2, env.max_links)))["next"]
    phase = torch.tensor(2 * torch.pi * 1.5 * env.control_period * 4)
    torch.testing.assert_close(td[CLOCK][0], torch.stack([phase.sin(), phase.cos()]).float())
    td.update({"_reset": torch.tensor([[False], [True]]), MORPHOLOGY: torch.tensor([[0], [1]])})
    after = env.reset(td)  # the reset robot's clock starts again, the other's runs on
    torch.testing.assert_close(after[CLOCK], torch.stack([td[CLOCK][0], torch.tensor([0.0, 1.0])]))
    env.close()


def _trajectory(morphologies, actions, masked_value=None, seed=0, **kwargs):
    env = _env(len(morphologies), max_links=actions.shape[-1], design=DE, **kwargs)
    env.set_seed(seed)
    td = _forced(env, morphologies)
    mask = td[ACTION_MASK]
    out = []
    for action in actions:
        if masked_value is not None:
            action = torch.where(mask, action, masked_value)
        td = env.step(td.set("action", action))["next"]
        out.append(td.select(TOKENS, "reward").clone())
    env.close()
    return torch.stack(out)


def test_masked_action_slots_do_not_affect_the_physics_of_robots_side_by_side():
    actions = torch.rand(12, 2, 16, generator=torch.Generator().manual_seed(1)) * 2 - 1
    plain = _trajectory([0, 1], actions, masked_value=torch.tensor(0.0))
    for garbage in (torch.tensor(1.0), torch.tensor(-7.5), torch.tensor(float("nan"))):
        assert torch.equal(_trajectory([0, 1], actions, masked_value=garbage)[TOKENS], plain[TOKENS])
    # ... while the real slots do move the robots (the comparison above could fail).
    assert not torch.equal(_trajectory([0, 1], -actions)[TOKENS], plain[TOKENS])
    assert plain[TOKENS][-1, :, 1:, FEATURE_INDEX["joint_rate"]].abs().sum() > 0


def test_same_seed_same_trajectories():
    def rollout(seed):
        env = _env(3, sampling="balanced")
        env.set_seed(seed)
        torch.manual_seed(0)
        out = env.rollout(8, break_when_any_done=False)
        env.close()
        return out
    first, again, other = rollout(0), rollout(0), rollout(1)
    assert torch.equal(first["next", TOKENS], again["next", TOKENS])
    assert torch.equal(first["design"], again["design"])
    assert not torch.equal(first["design"], other["design"])
    assert sorted(first[MORPHOLOGY][:, 0].flatten().tolist()) == [0, 1, 2]  # balanced: each once per round


def test_the_vertebrate_walks_exactly_as_in_the_vertebrate_env():
    """The grammar's thesis robot, its four hips driven, against BatchedWalkerEnv's robot, every
    link: the same physics, step for step."""
    design = DesignDistribution.fixed(0.18, 0.45)
    old = BatchedWalkerEnv(1, design=design, observation="full", episode_length=30)
    new = MorphologyWalkerEnv(1, (VERTEBRATE,), design=design, driven_joints=("axial_roll",), episode_length=30)
    a, b = old.reset(), new.reset()
    hips = torch.nonzero(b[ACTION_MASK][0]).flatten()
    assert len(hips) == 4
    actions = torch.rand(30, 1, 4, generator=torch.Generator().manual_seed(0)) * 2 - 1
    for action in actions:
        padded = torch.zeros(1, 15).index_copy(1, hips, action)
        a, b = old.step(a.set("action", action))["next"], new.step(b.set("action", padded))["next"]
        observation, tokens = a["observation"][0].double(), b[TOKENS][0].double()
        assert torch.equal(a["observation"][0, :6], b[TOKENS][0, 0, :6])  # the base, exactly
        assert torch.equal(a["reward"], b["reward"])
        bodies = observation[:90].reshape(15, 6)
        torch.testing.assert_close(tokens[1:, :3], bodies[1:, :3] - bodies[:1, :3], rtol=0, atol=1e-6)
        torch.testing.assert_close(tokens[1:, 3:6], bodies[1:, 3:], rtol=0, atol=1e-6)
        torch.testing.assert_close(tokens[hips, FEATURE_INDEX["joint_angle"]], observation[90:94], rtol=0, atol=1e-6)
    assert a["observation"][0, 0].abs() > 0.01 and b["truncated"].all() and a["truncated"].all()
    old.close()
    new.close()


@pytest.mark.parametrize("speed", [None, 3.0])
def test_the_motors_top_speed_holds_every_driven_joint_and_keeps_the_robot_on_the_ground(speed):
    """Targets jumping between the ends of their range drive a light robot's joints well past
    3 rad/s; motors with a top speed of 3 rad/s keep every joint within it, and the robot stays
    where it stands (a clamp on the joints' state instead flings robots: docs/grammar.md)."""
    env = _env(2, (TEN_LINKS,), design=DE, physics=PhysicsSettings(max_joint_speed=speed))
    td = env.reset()
    fastest, highest = 0.0, 0.0
    for step in range(12):
        td = env.step(td.set("action", torch.full((2, env.max_links), 1.0 if step % 2 else -1.0)))["next"]
        for simulation in env.simulations:
            links, joints = simulation.read()
            fastest = max(fastest, max(abs(rate) for rate in joints[1::2]))
            highest = max(highest, links[2])
    env.close()
    if speed is None:
        assert fastest > 3.0 * 1.5
    else:
        assert fastest <= speed * 1.05
        assert highest < 0.5


def test_reward_reads_the_root_token_and_orientations_are_rotations():
    env = _env(3, design=DE)
    env.set_seed(0)
    td = env.reset()
    for _ in range(5):
        td = env.step(td.set("action", torch.rand(3, 15) * 2 - 1))["next"]
    torch.testing.assert_close(td["reward"][:, 0], walking_reward(td[TOKENS][:, 0, :]).float())
    start = FEATURE_INDEX["r00"]
    columns = td[TOKENS][td[TOKEN_MASK]][:, start:start + 6].double().reshape(-1, 2, 3)
    torch.testing.assert_close(columns.norm(dim=-1), torch.ones(columns.shape[:2], dtype=torch.float64), atol=1e-5,
                               rtol=0)
    torch.testing.assert_close((columns[:, 0] * columns[:, 1]).sum(-1), torch.zeros(len(columns), dtype=torch.float64),
                               atol=1e-5, rtol=0)
    env.close()


def test_a_physics_fault_truncates_that_robot_only_and_repeats_its_last_tokens():
    env = _env(2, design=DE)
    env.set_seed(0)
    td = _forced(env, [0, 1])
    td = env.step(td.set("action", torch.full((2, 15), 0.5)))["next"]
    previous = td[TOKENS].clone()
    faulty = env.simulations[1]
    pybullet.resetBasePositionAndOrientation(faulty.body.body_id, (1e4, 0, 1), (0, 0, 0, 1),
                                             physicsClientId=faulty.client)
    out = env.step(td.set("action", torch.zeros(2, 15)))["next"]
    assert out["physics_fault"].flatten().tolist() == [False, True]
    assert out["truncated"].flatten().tolist() == [False, True]
    assert torch.equal(out[TOKENS][1], previous[1]) and torch.isfinite(out["reward"]).all()
    env.close()


@pytest.mark.parametrize(("make", "message"), [
    (lambda: _env(max_links=12), r"morphology 0 has 15 links, more than max_links=12"),
    (lambda: _env(morphologies=()), "morphology set is empty"),
    (lambda: _env(morphologies=(VERTEBRATE, "make_robot")), r"morphology 1 is not a Morphology: 'make_robot'"),
    (lambda: _env(driven_joints=("elbow",)), "elbow"),
    (lambda: _env(morphologies=(SIX_LINKS,), driven_joints=("axial_roll",)), "morphology 0 has no hinge"),
    (lambda: _env(sampling="round_robin"), "round_robin"),
    (lambda: _env(max_links=0), "max_links"),
    (lambda: _env(clock_frequency=0.0), "clock_frequency must be a positive number of Hz or None, got 0.0"),
    (lambda: _env(token_layout=StructuralLayout(2, 4)), r"morphology 0 does not fit the token layout: link 'body_2'"),
    (lambda: _env(token_layout=StructuralLayout(3, 2)), r"morphology 0 does not fit .* leg_slots=2"),
    (lambda: _env(token_layout=StructuralLayout(3, 3), max_links=14), r"morphology 0 puts a link at slot 14"),
    (lambda: _env(token_layout="structural"), "token_layout must be None .* got 'structural'"),
    (lambda: StructuralLayout(0, 3), "body_slots must be a positive integer, got 0"),
    (lambda: _forced(_env(2), [0, 7]), "unknown morphology index 7 for robot 1"),
    (lambda: _forced(_env(2), [-1, 0]), "unknown morphology index -1 for robot 0"),
])
def test_bad_input_raises_naming_the_value(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def _grammar_config(*overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["robot=grammar", "robot.split.train_size=3",
                                            "robot.split.held_out_size=2", *overrides])


def test_the_grammar_config_builds_the_env_of_its_split():
    cfg = _grammar_config("robot.sampling=balanced", "design=de")
    env = make_morphology_env(cfg, 2)
    assert len(env.morphologies) == 3 and env.sampling == "balanced"
    assert env.max_links == HELD_OUT_LIMITS.max_links == 5 + 2 * 3 * 4  # held-out robots fit the same tokens
    assert env.design_distribution.is_deterministic
    check_env_specs(env, seed=0)
    env.close()
    structural = make_morphology_env(_grammar_config("robot.token_layout=structural"), 1)
    assert structural.token_layout == StructuralLayout(body_slots=5, leg_slots=4)
    assert structural.max_links == 5 + 2 * 3 * 4  # the same slots as packed: one block per link a robot may have
    structural.close()
    with pytest.raises(ValueError, match="robot.token_layout must be one of .* got 'diagonal'"):
        make_morphology_env(_grammar_config("robot.token_layout=diagonal"), 1)
    held_out = make_morphology_env(_grammar_config("robot.morphologies=held_out", "robot.max_links=40"), 1)
    assert len(held_out.morphologies) == 2 and held_out.max_links == 40
    held_out.close()
    with pytest.raises(ValueError, match="'test'"):
        make_morphology_env(_grammar_config("robot.morphologies=test"), 1)
    with pytest.raises(ValueError, match="empty split|held_out_size=0"):
        make_morphology_env(_grammar_config("robot.split.held_out_size=0"), 1)
    with pytest.raises(ValueError, match="robot=grammar builds a MorphologyWalkerEnv"):
        env_kwargs(cfg)
