"""The policies in pretrained/ load with today's code and act on the env they were trained on, and
pretrained/README.md says what each one is (a checkpoint format change must keep them loadable)."""

from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.checkpoint import load_policy

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"
POLICIES = sorted(PRETRAINED.glob("*.pt"))


def test_there_are_pretrained_policies_and_each_is_described():
    assert {path.name for path in POLICIES} >= {"se-trpo-seed0.pt", "se-moe-trpo-seed0.pt",
                                                "grammar-specialist-train0.pt"}
    readme = (PRETRAINED / "README.md").read_text()
    assert all(f"`{path.name}`" in readme for path in POLICIES)


@pytest.mark.parametrize("path", POLICIES, ids=[path.stem for path in POLICIES])
def test_a_pretrained_policy_loads_and_acts_on_its_env(path):
    loaded = load_policy(path)
    env = loaded.env_class(2, **loaded.env_kwargs)
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            steps = env.rollout(3, loaded.policy)  # (the env clips a mean beyond [-1, 1], as in training)
    finally:
        env.close()
    assert steps["action"].shape[:2] == (2, 3) and torch.isfinite(steps["action"]).all()
    assert torch.isfinite(steps["next", "reward"]).all()
