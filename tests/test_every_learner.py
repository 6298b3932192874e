"""Every learner ``algo=`` names takes an update on a tiny real batch, and one rebuilt from its
state dict continues exactly: the same next update, the same weights. Tiny networks and batches,
so every learner a user can choose is exercised in seconds."""

import copy

import pytest
import torch
from hydra import compose, initialize_config_dir
from test_config_groups import CONF
from test_distillation import SPLIT, write_teacher

from unipolicy_rl.collectors import truncate_last_step
from unipolicy_rl.env_factories import env_builder
from unipolicy_rl.factories import make_learner, probe_dimensions
from unipolicy_rl.registry import LEARNER_NAMES

TINY = ["robot.episode_length=10", "algo.actor_hidden=[8]", "algo.critic_hidden=[8]"]
# What makes each learner take its gradient steps on 2 robots x 10 steps, quickly.
SETTINGS = {
    "trpo": ["algo.critic_epochs=1"],
    "ppo": ["algo.critic_epochs=1", "algo.policy_epochs=1"],
    "sac": ["algo.learning_starts=8", "algo.batch_size=8"],
    "crossq": ["algo.learning_starts=8", "algo.batch_size=8"],
    "redq": ["algo.learning_starts=8", "algo.batch_size=8", "algo.updates_per_step=1", "algo.num_critics=3"],
    "distill": [*SPLIT, "policy=token_modular", "algo.batch_size=8", "algo.updates_per_epoch=2"],
}


def config(*overrides):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=[*TINY, *overrides])


def real_batch(cfg, policy, seed: int):
    """One epoch of 2 robots, as the real collector hands it to the learner."""
    env_class, kwargs = env_builder(cfg)
    env = env_class(2, **{**kwargs, "episode_length": None})
    env.set_seed(seed)
    with torch.no_grad():
        batch = env.rollout(cfg.robot.episode_length, policy, break_when_any_done=False)
    env.close()
    return truncate_last_step(batch)


def weights(learner) -> dict[str, torch.Tensor]:
    return {key: value.clone() for key, value in learner.policy.state_dict().items()}


def test_every_registered_learner_is_tried_here():
    assert set(SETTINGS) == set(LEARNER_NAMES)


@pytest.mark.parametrize("name", LEARNER_NAMES)
def test_a_learner_takes_an_update_and_one_rebuilt_from_its_state_continues_exactly(name, tmp_path):
    overrides = [f"algo={name}", *SETTINGS[name]]
    if name == "distill":
        teachers = [write_teacher(tmp_path / f"train{index}.pt", f"robot.specialist={index}", seed=index)
                    for index in (0, 1)]
        overrides.append(f"algo.teachers=[{teachers[0]},{teachers[1]}]")
    cfg = config(*overrides)
    dims = probe_dimensions(cfg)
    torch.manual_seed(0)
    learner = make_learner(cfg, *dims)
    before = weights(learner)
    first = real_batch(cfg, learner.policy, seed=0)
    metrics = learner.update(first)
    learner.refresh_observation_normalizer(first)
    assert metrics and all(isinstance(value, float) for value in metrics.values())
    moved = weights(learner)
    assert any(not torch.equal(before[key], moved[key]) for key in before), "the update changed no weight"

    torch.manual_seed(1)
    rebuilt = make_learner(cfg, *dims)
    rebuilt.load_state_dict(copy.deepcopy(learner.state_dict()))
    assert all(torch.equal(value, weights(rebuilt)[key]) for key, value in moved.items())
    second = real_batch(cfg, learner.policy, seed=1)
    torch.manual_seed(2)
    expected = learner.update(second.clone())
    torch.manual_seed(2)
    resumed = rebuilt.update(second.clone())
    assert resumed == expected
    assert all(torch.equal(value, weights(rebuilt)[key]) for key, value in weights(learner).items())
    learner.close()
    rebuilt.close()
