"""Every setting is checked when a run starts: the composed config, walked key by key."""

import copy
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from unipolicy_rl.validation import validate_config

ROOT = Path(__file__).resolve().parents[1]
# A model source composes every key a real source has, and its world model's.
SOURCES = (["source=moe"], ["source=moe", "world_model=moe_thesis"], ["source=pce"],
           ["source=pce", "world_model=pce_thesis"], ["source=pce", "world_model=pce_sparse"])
# Values a number is tried with; every checked key must refuse at least one of them.
INVALID_CANDIDATES = (-1, 0, 10**9)
# Numeric keys any value of which (among the candidates) is fine, and why.
ACCEPTS_ANY = {
    "world_model.model.max_log_var": "any initial bound above min_log_var (the pair is checked; -1, 0 and 1e9 all are)",
}


def composed(overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def numeric_leaves(node, prefix=""):
    for key in node:
        value = node._get_node(key)
        path = f"{prefix}{key}"
        if OmegaConf.is_dict(value):
            yield from numeric_leaves(value, path + ".")
        elif OmegaConf.is_list(value) or value._is_interpolation():
            continue
        elif isinstance(value._value(), (int, float)) and not isinstance(value._value(), bool):
            yield path


@pytest.mark.parametrize("overrides", SOURCES, ids=lambda o: o[-1])
def test_every_numeric_setting_refuses_an_invalid_value_naming_its_key(overrides):
    cfg = composed(overrides)
    validate_config(cfg)  # the defaults are valid
    unchecked = []
    for key in numeric_leaves(cfg):
        refused = []
        for candidate in INVALID_CANDIDATES:
            bad = copy.deepcopy(cfg)
            OmegaConf.update(bad, key, candidate)
            try:
                validate_config(bad)
            except ValueError as err:
                refused.append(candidate)
                # The message names the setting: its key (or, for a dataclass, its group) and field.
                assert key.split(".")[-1] in str(err) or key.split(".")[0] in str(err), (key, str(err))
                break
        if not refused and key not in ACCEPTS_ANY:
            unchecked.append(key)
    assert not unchecked, f"settings that accept any value, with no check: {unchecked}"


# One launch of train.py in the fast tests; the others (slow) show the same for other kinds of key.
@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("epochs=-1", "epochs must be an integer >= 1, got -1"),
        pytest.param("algo.gamma=1.5", "algo.gamma must lie in (0, 1], got 1.5", marks=pytest.mark.slow),
        pytest.param("evaluation.grid=0", "evaluation.grid must be an integer >= 1, got 0", marks=pytest.mark.slow),
        pytest.param("robot=grammar policy=mlp", "policy=mlp reads one robot's flat observation, but robot=grammar",
                     marks=pytest.mark.slow),
    ],
)
def test_a_bad_override_stops_train_py_before_any_robot_is_built(tmp_path, override, message):
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), *override.split(), f"hydra.run.dir={tmp_path}"],
                            cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode != 0
    assert message in result.stderr
    assert not (tmp_path / "metrics.csv").exists()


# ---- Each check in one place: validation's rules, which the factories that read the same keys run too


def test_workers_must_share_the_episodes_evenly_one_rule_for_validation_and_the_collector_factory():
    from unipolicy_rl.factories import robots_per_worker

    cfg = composed(["episodes_per_epoch=9", "workers=2"])
    message = r"episodes_per_epoch \(9\) must be a multiple of workers \(2\)"
    with pytest.raises(ValueError, match=message):
        validate_config(cfg)
    with pytest.raises(ValueError, match=message):  # a direct call, validate_config never run
        robots_per_worker(cfg)
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        robots_per_worker(composed(["workers=0"]))  # its own rule first: no division by zero
    assert robots_per_worker(composed(["episodes_per_epoch=10", "workers=2"])) == 5


def test_algo_name_is_one_rule_for_validation_and_the_learner_factory():
    from unipolicy_rl.factories import make_learner

    cfg = composed(["algo.name=a2c"])
    names = r"\['crossq', 'distill', 'ppo', 'redq', 'sac', 'trpo'\]"
    with pytest.raises(ValueError, match=rf"algo.name must be one of {names}, got 'a2c'"):
        validate_config(cfg)
    with pytest.raises(ValueError, match=rf"algo.name must be one of {names}, got 'a2c'"):
        make_learner(cfg, 18, 4)


def test_source_kind_and_a_model_source_s_groups_are_checked_by_validation():
    with pytest.raises(ValueError, match=r"source.kind must be one of \['model', 'real'\], got 'imagined'"):
        validate_config(composed(["source.kind=imagined"]))
    # make_dynamics_model relies on this check (train.py validates first).
    with pytest.raises(ValueError, match="a model-based source needs a world_model config"):
        validate_config(composed(["source=moe", "~world_model"]))
    with pytest.raises(ValueError, match="a model-based source needs a imagination config"):
        validate_config(composed(["source=moe", "~imagination"]))
    # A real source reads no world model: one chosen with it is refused, not ignored.
    with pytest.raises(ValueError, match="world_model is read by a model-based source only, and source=se"):
        validate_config(composed(["source=se", "world_model=moe"]))


def test_device_is_checked_once_by_its_resolver_which_validation_runs():
    with pytest.raises(ValueError, match=r"device: device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got 'tpu'"):
        validate_config(composed(["device=tpu"]))
    validate_config(composed(["device=cpu"]))


def test_check_settings_runs_only_the_rules_of_the_keys_named():
    from unipolicy_rl.validation import JOINT_RULES, RULES, check_settings

    cfg = composed(["epochs=-1", "episodes_per_epoch=9"])
    check_settings(cfg, "seed", "workers")  # neither bad key named; the joint rule needs both of its keys
    with pytest.raises(ValueError, match="epochs must be an integer >= 1, got -1"):
        check_settings(cfg, "epochs")
    with pytest.raises(ValueError, match="must be a multiple of workers"):
        check_settings(cfg, "episodes_per_epoch", "workers")
    # Every key a rule reads exists in the composed config of a model source.
    model = composed(["source=moe"])
    for key in [*RULES, *(key for joint in JOINT_RULES for key in joint)]:
        assert OmegaConf.select(model, key) is not None, key


# ---- robot=grammar and the token policies: combinations that cannot run are refused by name
GRAMMAR = ["robot=grammar", "robot.split.train_size=3", "robot.split.held_out_size=2"]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["robot=grammar", "policy=mlp"],
         r"use a token policy \(policy=token_transformer or policy=token_mlp or policy=token_modular\)"),
        (["policy=token_transformer"], "policy=token_transformer reads link tokens, which robot=vertebrate does not "
                                       "write: train it with robot=grammar"),
        ([*GRAMMAR, "policy=token_mlp", "source=pce"],
         r"source=pce with robot=grammar: its world model, PCEDynamics \(world_model.model_state=full\), predicts "
         "one robot's flat state"),
        ([*GRAMMAR, "policy=token_mlp", "source=moe", "world_model=moe_thesis"],
         r"its world model, CellEnsemble \(world_model.model_state=thesis\)"),
        (["source=moe", "world_model.model_state=tokens"],
         "world_model.model_state=tokens .GaussianEnsemble. models link tokens, which robot=vertebrate does not write"),
        ([*GRAMMAR, "policy=token_mlp", "source=moe", "world_model.model.embedding=0"],
         "world_model.model: embedding must be a positive integer, got 0"),
        ([*GRAMMAR, "policy=token_mlp", "algo=sac"],
         "algo=sac with robot=grammar: the token policies are Gaussians that only "
         "algo=trpo or algo=ppo or algo=distill train"),
        (["policy.name=cnn"],
         r"policy.name must be one of \['mlp', 'token_mlp', 'token_modular', 'token_transformer'\], got 'cnn'"),
        (["algo.fisher_fraction=0"], r"algo: fisher_fraction must lie in \(0, 1\]"),
        (["algo.fisher_fraction=1.5"], r"algo: fisher_fraction must lie in \(0, 1\]"),
        ([*GRAMMAR, "policy=token_mlp", "evaluation.morphologies=test"], "evaluation.morphologies must be one of"),
        ([*GRAMMAR, "policy=token_mlp", "robot.sampling=random"], "robot.sampling must be one of"),
        ([*GRAMMAR, "policy=token_mlp", "robot.training_morphologies=4"],
         r"robot.training_morphologies must be null or an integer in \[1, 3\]"),
        ([*GRAMMAR, "policy=token_mlp", "robot.morphologies=held_out", "robot.specialist=2"],
         r"robot.specialist must be null or an index in \[0, 1\] of the 2 morphologies of "
         "robot.morphologies=held_out, got 2"),
        (["+robot.kind=snake"], "robot.kind must be one of"),
        ([*GRAMMAR, "policy=token_transformer", "policy.critic=attention"],
         r"policy.critic must be one of \('transformer', 'pooled', 'padded_mlp'\), got 'attention'"),
        (["algo.advantage_groups=morphology"],
         "algo.advantage_groups=morphology groups the batch by the robot's morphology, which only robot=grammar"),
        ([*GRAMMAR, "policy=token_mlp", "algo.advantage_groups=design"],
         r"algo.advantage_groups must be one of \['morphology'\] or null, got 'design'"),
        ([*GRAMMAR, "policy=token_mlp", "algo.advantage_groups=morphology", "algo.normalize_advantage=false"],
         "algo.advantage_groups=morphology standardises the advantages within groups, "
         "but algo.normalize_advantage=false"),
        ([*GRAMMAR, "policy=token_mlp", "policy.critic=transformer"],
         "policy.critic=transformer takes its sizes from policy.critic_network or policy.network, and "
         "policy=token_mlp has neither"),
        ([*GRAMMAR, "policy=token_modular", "robot.clock_frequency=-1"],
         r"robot.clock_frequency must lie in \(0, inf\) or null, got -1"),
        ([*GRAMMAR, "policy=token_transformer", "robot.clock_frequency=1.5"],
         "robot.clock_frequency=1.5 adds a gait clock only policy=token_modular reads"),
        ([*GRAMMAR, "policy=token_modular", "source=moe", "robot.clock_frequency=1.5"],
         "robot.clock_frequency=1.5 with source=moe: the world model's imagined steps carry no clock"),
    ],
)
def test_a_robot_and_policy_that_cannot_train_together_are_refused_by_name(overrides, message):
    with pytest.raises(ValueError, match=message):
        validate_config(composed(overrides))


def test_a_grammar_run_with_a_token_policy_is_valid():
    for policy in ("token_transformer", "token_mlp"):
        validate_config(composed([*GRAMMAR, f"policy={policy}", "robot.training_morphologies=2",
                                  "evaluation.morphologies=all", "algo.fisher_fraction=0.2"]))
    validate_config(composed([*GRAMMAR, "policy=token_transformer", "algo.advantage_groups=morphology"]))
    validate_config(composed([*GRAMMAR, "policy=token_modular", "robot.clock_frequency=1.5"]))


def test_a_model_based_grammar_run_takes_the_ensemble_conditioned_on_the_morphology():
    for policy in ("token_transformer", "token_mlp"):
        cfg = composed([*GRAMMAR, f"policy={policy}", "source=moe"])
        validate_config(cfg)
        assert cfg.world_model.model._target_ == "unipolicy_rl.world_models.TokenEnsemble"
        assert cfg.world_model.model_state == "tokens"
    # The vertebrate's world_model=moe stays the flat ensemble.
    assert composed(["source=moe"]).world_model.model._target_ == "unipolicy_rl.world_models.GaussianEnsemble"


def test_a_specialist_run_trains_and_evaluates_on_one_morphology_of_its_side():
    from unipolicy_rl.env_factories import grammar_morphologies, morphology_env_kwargs

    cfg = composed([*GRAMMAR, "policy=token_mlp", "robot.morphologies=held_out", "robot.specialist=1",
                    "evaluation.morphologies=held_out"])
    validate_config(cfg)
    split, _ = grammar_morphologies(cfg, "all")
    assert morphology_env_kwargs(cfg)["morphologies"] == (split.held_out[1],)
    assert morphology_env_kwargs(cfg, cfg.evaluation.morphologies)["morphologies"] == (split.held_out[1],)
    assert morphology_env_kwargs(cfg, "train")["morphologies"] == split.train  # another side stays whole


def test_a_fit_precision_other_than_float32_bfloat16_or_auto_is_refused_at_start_up():
    validate_config(composed(["source=moe", "world_model.trainer.precision=bfloat16"]))
    validate_config(composed(["source=moe", "world_model.trainer.precision=auto"]))
    with pytest.raises(ValueError, match=r"world_model.trainer.*precision must be one of "
                                         r"\['auto', 'bfloat16', 'float32'\], got 'float16'"):
        validate_config(composed(["source=moe", "world_model.trainer.precision=float16"]))


@pytest.mark.parametrize("setting", ["disagreement_cut", "disagreement_penalty"])
def test_a_disagreement_setting_on_a_model_whose_members_cannot_disagree_is_refused_before_training(setting):
    validate_config(composed(["source=moe", f"imagination.{setting}=1.0"]))  # the ensemble's members can
    with pytest.raises(ValueError, match=rf"imagination\.{setting} .*CellEnsemble cannot.*one per cell"):
        validate_config(composed(["source=moe", "world_model=moe_thesis", f"imagination.{setting}=1.0"]))
