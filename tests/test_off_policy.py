"""SAC, CrossQ and REDQ as learners: each takes a correct step, moves its targets as configured,
meets its entropy target, acts deterministically with tanh(loc), refuses bad settings by name,
and a SAC run resumes exactly; on a world model (MBPO) the learner takes its earned steps on the
model's branches, mixing real and model data at the configured share, and an MBPO run resumes
exactly."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from test_train import run_train, straight_and_resumed
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.collectors.real import IMAGINED, label
from unipolicy_rl.factories import make_learner
from unipolicy_rl.learners import Learner, OffPolicyLearner
from unipolicy_rl.networks import WarmedUpBatchRenorm1d

ROOT = Path(__file__).resolve().parents[1]


def config(algo: str, *overrides: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=[f"algo={algo}", "algo.actor_hidden=[32]", "algo.critic_hidden=[32]",
                                            "algo.batch_size=32", "algo.learning_starts=0",
                                            "algo.buffer_capacity=10000", *overrides])


def transitions(n: int, observation_dim: int, action_dim: int, seed: int = 0, terminal: bool = False) -> TensorDict:
    """Random transitions of a toy problem whose reward is ``-4 (action - 0.5)^2`` (``terminal``: every
    one ends its episode, so an action's value is its reward alone)."""
    g = torch.Generator().manual_seed(seed)
    observation = torch.randn(n, observation_dim, generator=g)
    action = torch.rand(n, action_dim, generator=g) * 2 - 1
    rewards = -4 * (action - 0.5).pow(2).sum(-1, keepdim=True)
    flags = torch.full((n, 1), terminal)
    return TensorDict({"observation": observation, "action": action,
                       "next": {"observation": torch.randn(n, observation_dim, generator=g), "reward": rewards,
                                "done": flags, "terminated": flags}}, batch_size=[n])


@pytest.mark.parametrize("algo", ["sac", "crossq", "redq"])
def test_each_learner_takes_steps_that_lower_its_critic_loss(algo):
    torch.manual_seed(0)
    learner = make_learner(config(algo, "algo.updates_per_step=1"), 3, 1)
    assert isinstance(learner, OffPolicyLearner) and isinstance(learner, Learner)
    data = transitions(48, 3, 1)
    first = learner.update(data)
    for _ in range(3):
        last = learner.update(data)
    assert learner.gradient_steps == 4 * 48  # one step per new transition (UTD 1)
    assert last["train/loss_critic"] < first["train/loss_critic"]
    assert last["train/buffer_size"] == 4 * 48


def test_sac_target_critics_follow_the_critics_at_the_polyak_rate_and_crossq_has_none():
    torch.manual_seed(0)
    learner = make_learner(config("sac", "algo.target_update_rate=0.1", "algo.updates_per_step=1"), 3, 1)
    loss = learner.loss
    online = loss.qvalue_network_params.flatten_keys()
    target = loss.target_qvalue_network_params.flatten_keys()
    before = {key: value.detach().clone() for key, value in target.items()}
    learner.update(transitions(1, 3, 1))  # one transition: one gradient step
    for key, value in target.items():
        expected = 0.9 * before[key] + 0.1 * online[key].detach()
        torch.testing.assert_close(value.detach(), expected)
    assert any(not torch.equal(value.detach(), before[key]) for key, value in target.items())
    crossq = make_learner(config("crossq"), 3, 1)
    assert crossq.target_update is None


def test_batch_renormalisation_keeps_its_corrections_clamped_long_after_its_warm_up():
    """After the warm-up a batch 10x wider than the running statistics is scaled by at most
    ``max_r``: with TorchRL's own count the factor on ``r`` grows with every further warm-up's
    worth of steps and the output widens past the clamp."""
    torch.manual_seed(0)
    layer = WarmedUpBatchRenorm1d(4, warmup_steps=5, momentum=0.5)
    for _ in range(20):  # four warm-ups' worth of batches from N(0, 1)
        layer(torch.randn(256, 4))
    wide = layer(torch.randn(256, 4) * 10)
    assert wide.std(0).max().item() <= layer.max_r * 1.01
    assert wide.std(0).min().item() >= layer.max_r * 0.99  # the clamp is reached, not skipped
    assert int(layer.num_batches_tracked) == 5


def test_crossq_critics_renormalise_after_the_configured_warm_up():
    learner = make_learner(config("crossq", "algo.batch_renorm_warmup=123"), 3, 1)
    layers = [m for m in learner.loss.qvalue_network.modules() if isinstance(m, WarmedUpBatchRenorm1d)]
    assert len(layers) == 2 and all(layer.warmup_steps == 123 for layer in layers)  # input, one hidden layer
    params = learner.loss.qvalue_network_params
    key = next(k for k in params.keys(True, True) if k[-1] == "num_batches_tracked")
    learner.update(transitions(200, 3, 1))  # 200 gradient steps: the count stops at the warm-up
    assert (params.get(key) == 123).all()


@pytest.mark.slow
def test_the_temperature_holds_the_policys_entropy_at_its_target():
    """One action, a reward peaked at 0.5: the actor would narrow without end, the learned
    temperature stops it where the entropy meets the target (``auto``: -1 for one action)."""
    torch.manual_seed(0)
    learner = make_learner(config("sac", "algo.learning_rate=0.003", "algo.updates_per_step=1"), 2, 1)
    for seed in range(10):
        learner.update(transitions(200, 2, 1, seed=seed, terminal=True))
    observations = TensorDict({"observation": torch.randn(4000, 2)}, batch_size=[4000])
    with torch.no_grad():
        log_prob = learner.policy(observations)["action_log_prob"]
    assert float(-log_prob.mean()) == pytest.approx(-1.0, abs=0.3)


def test_the_deterministic_action_is_the_tanh_of_the_mean():
    learner = make_learner(config("sac"), 3, 2)
    observation = TensorDict({"observation": torch.randn(5, 3)}, batch_size=[5])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        out = learner.policy(observation.clone())
    torch.testing.assert_close(out["action"], torch.tanh(out["loc"]))


def network_outputs(learner: OffPolicyLearner, observations: torch.Tensor, actions: torch.Tensor) -> list[torch.Tensor]:
    """On raw observations: the actor's Gaussian (loc, scale), then every critic's value (online,
    then target), each in evaluation and in training mode (batch statistics; run on copies of the
    critics' parameters, so the learner's running statistics do not move)."""
    probe = TensorDict({"observation": observations.clone()}, [len(observations)])
    gaussian = learner._gaussian(probe)
    outputs = [gaussian.loc, gaussian.scale]
    data = learner.normalizer(TensorDict({"observation": observations.clone(), "action": actions},
                                         [len(observations)]))
    critic = learner.loss.qvalue_network
    for name in ("qvalue_network_params", "target_qvalue_network_params"):
        params = getattr(learner.loss, name, None)
        if params is None:
            continue
        for member in range(params.shape[0]):
            for training in (False, True):
                with params[member].detach().clone().to_module(critic):
                    critic.train(training)
                    outputs.append(critic(data.clone())["state_action_value"])
    critic.train(False)
    return outputs


@pytest.mark.parametrize("algo", ["sac", "crossq", "redq"])
def test_a_preserving_refresh_leaves_the_actor_and_every_critic_as_they_were(algo):
    """``normalizer_refresh=preserve`` re-expresses the actor's and the critics' first layers (CrossQ:
    its input's running statistics) so a refresh to very different statistics changes no output
    on raw observations; ``jump``, the same refresh, changes them."""
    changes = {}
    for mode in ("preserve", "jump"):
        torch.manual_seed(0)
        learner = make_learner(config(algo, f"algo.normalizer_refresh={mode}", "algo.updates_per_step=1"), 3, 1)
        data = transitions(64, 3, 1)
        learner.refresh_observation_normalizer(data)
        learner.update(data)  # the critics (and CrossQ's running statistics) move off their start
        params = learner.loss.qvalue_network_params  # CrossQ: its warm-up over, r and d at work
        for key in [k for k in params.keys(True, True) if k[-1] == "num_batches_tracked"]:
            params.get(key).fill_(WarmedUpBatchRenorm1d(1).warmup_steps)
        g = torch.Generator().manual_seed(1)
        observations = torch.randn(256, 3, generator=g) * 2 + 1
        actions = torch.rand(256, 1, generator=g) * 2 - 1
        before = network_outputs(learner, observations, actions)
        shifted = data.clone()
        shifted["observation"] = shifted["observation"] * 5 + 3  # statistics far from the first ones
        metrics = learner.refresh_observation_normalizer(shifted)
        after = network_outputs(learner, observations, actions)
        changes[mode] = max(float((a - b).abs().max().detach()) for a, b in zip(after, before, strict=True))
        if mode == "preserve":
            assert metrics["train/refresh_kl"] < 1e-8
            for a, b in zip(after, before, strict=True):
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
        else:
            assert metrics["train/refresh_kl"] > 1e-3
    assert changes["jump"] > 100 * max(changes["preserve"], 1e-6)


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("algo.num_critics=0", "algo.num_critics must be an integer >= 1, got 0"),
        ("algo.updates_per_step=0.5", "algo.updates_per_step .* must be >= 1, got 0.5"),
        ("algo.batch_size=0", "algo.batch_size must be an integer >= 1, got 0"),
        ("algo.target_update_rate=null", "target_update_rate must be set for sac"),
        ("algo.real_data_share=1.5", "algo.real_data_share must lie in \\[0, 1\\], got 1.5"),
        ("algo.real_data_share=-0.1", "algo.real_data_share must lie in \\[0, 1\\], got -0.1"),
        ("algo.normalizer_refresh=keep", "algo.normalizer_refresh must be one of .*, got 'keep'"),
        ("algo.batch_renorm_warmup=-1", "algo.batch_renorm_warmup must be an integer >= 0, got -1"),
    ],
)
def test_bad_learner_settings_are_refused_by_name(override, match):
    with pytest.raises(ValueError, match=match):
        make_learner(config("sac", override), 3, 1)


def mbpo_learner(*overrides: str) -> OffPolicyLearner:
    cfg = config("sac", "source=moe", "imagination=mbpo", "algo.updates_per_step=2", *overrides)
    return make_learner(cfg, 3, 1)


def marked(data: TensorDict, mark: float) -> TensorDict:
    data["observation"][:, 0] = mark
    return data


def test_mbpo_takes_the_steps_real_data_earned_when_the_models_branches_come():
    torch.manual_seed(0)
    learner = mbpo_learner()
    assert learner.model_based
    metrics = learner.update(transitions(50, 3, 1))  # real: stored, 2 x 50 steps earned, none taken yet
    assert learner.gradient_steps == 0 and metrics["train/buffer_size"] == 50
    metrics = learner.update(label(transitions(300, 3, 1, seed=1), IMAGINED))
    assert learner.gradient_steps == 100
    assert metrics["train/model_buffer_size"] == 300 and metrics["train/buffer_size"] == 50
    assert "train/loss_critic" in metrics
    learner.update(label(transitions(300, 3, 1, seed=2), IMAGINED))  # nothing earned since: data only
    assert learner.gradient_steps == 100


@pytest.mark.parametrize("share", [0.0, 0.25, 1.0])
def test_an_mbpo_minibatch_draws_the_real_data_share_from_real_transitions(share):
    torch.manual_seed(0)
    learner = mbpo_learner(f"algo.real_data_share={share}", "algo.learning_starts=1000")  # no steps taken
    learner.update(marked(transitions(100, 3, 1), 1.0))
    learner.update(label(marked(transitions(100, 3, 1, seed=1), -1.0), IMAGINED))
    minibatch = learner.sample_minibatch()
    assert minibatch.batch_size == torch.Size([32])
    assert int((minibatch["observation"][:, 0] == 1.0).sum()) == round(32 * share)
    assert int((minibatch["observation"][:, 0] == -1.0).sum()) == 32 - round(32 * share)


def test_a_model_free_learner_refuses_imagined_batches_by_name():
    learner = make_learner(config("sac"), 3, 1)
    with pytest.raises(ValueError, match="model_based=False"):
        learner.update(label(transitions(10, 3, 1), IMAGINED))


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("imagination=branch", "imagination.train_on_real=false"),
        ("imagination.stopping.max_updates=3", "one imagined batch per model fit"),
    ],
)
def test_an_imagination_mbpo_cannot_learn_from_is_refused_by_name(override, match):
    with pytest.raises(ValueError, match=match):
        make_learner(config("sac", "source=moe", "imagination=mbpo", override), 3, 1)


SAC_TINY = ["algo=sac", "episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=1", "progress_bar=false",
            "workers=1", "algo.actor_hidden=[16]", "algo.critic_hidden=[16]", "algo.batch_size=8",
            "algo.learning_starts=10", "algo.buffer_capacity=1000", "algo.updates_per_step=2"]


@pytest.mark.slow
def test_a_sac_run_resumes_exactly_and_refuses_bad_settings_at_start_up(tmp_path):
    straight, resumed, _ = straight_and_resumed(tmp_path, SAC_TINY, first=2, total=3)
    a, b = straight["learner"], resumed["learner"]
    assert a["gradient_steps"] == b["gradient_steps"] == 2 * 3 * 20
    for key, value in a["loss"].items():
        assert torch.equal(value, b["loss"][key]), f"{key} differs after resume"
    refused = run_train(*SAC_TINY, "algo.num_critics=0", "epochs=1", f"hydra.run.dir={tmp_path / 'bad'}")
    assert refused.returncode != 0 and "algo.num_critics must be an integer >= 1, got 0" in refused.stderr
    assert not (tmp_path / "bad" / "metrics.csv").exists()


MBPO_TINY = [*SAC_TINY, "source=moe", "imagination=mbpo", "imagination.steps_per_batch=60",
             "world_model.model.members=3", "world_model.model.elites=2", "world_model.model.hidden=[8]",
             "world_model.trainer.max_epochs=2", "algo.model_buffer_capacity=500"]


@pytest.mark.slow
def test_an_mbpo_run_resumes_exactly(tmp_path):
    straight, resumed, _ = straight_and_resumed(tmp_path, MBPO_TINY, first=2, total=3)
    a, b = straight, resumed
    assert a["learner"]["gradient_steps"] == b["learner"]["gradient_steps"] == 2 * 3 * 20
    for key, value in a["learner"]["loss"].items():
        assert torch.equal(value, b["learner"]["loss"][key]), f"{key} differs after resume"
    for key, value in a["world_model"].items():
        assert torch.equal(value, b["world_model"][key]), f"model {key} differs after resume"
    # (source=moe algo=sac alone selects imagination=mbpo; an on-policy imagination chosen by hand is refused)
    refused = run_train(*SAC_TINY, "source=moe", "imagination=recent_branch", "epochs=1",
                        f"hydra.run.dir={tmp_path / 'bad'}")
    assert refused.returncode != 0 and "imagination.train_on_real=false" in refused.stderr


@pytest.mark.slow
def test_mbpo_runs_on_the_polynomial_chaos_world_model_too(tmp_path):
    run = run_train(*SAC_TINY, "source=pce", "imagination=mbpo", "imagination.steps_per_batch=60", "epochs=2",
                    f"hydra.run.dir={tmp_path}")
    assert run.returncode == 0, run.stderr
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["learner"]["gradient_steps"] == 2 * 2 * 20  # UTD 2 x 20 real steps, per epoch
    assert state["config"]["world_model"]["model"]["_target_"].endswith("PCEDynamics")
