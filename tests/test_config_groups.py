"""Every option of every config group composes and passes start-up validation, and the defaults a
choice implies are the ones that run: ``robot=grammar`` alone trains its token policy, an
off-policy learner on a model source alone trains as MBPO."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from unipolicy_rl.validation import validate_config

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
# A small grammar split: the validation draws it (the default 32 + 16 robots take longer).
GRAMMAR = ["robot=grammar", "robot.split.train_size=3", "robot.split.held_out_size=2"]
# What an option needs beside it to be a run validation accepts (an option alone otherwise).
COMPANIONS: dict[str, list[str]] = {
    "algo=distill": [*GRAMMAR, "algo.teachers=[teacher.pt]"],
    "imagination=mbpo": ["source=moe", "algo=sac"],
    "imagination=short_branch": ["source=pce"],  # (it updates on real batches too: the PCE's inline critic fit)
    **{f"policy={name}": GRAMMAR for name in ("token_mlp", "token_modular", "token_transformer")},
    "robot=grammar": GRAMMAR[1:],
    **{f"world_model={name}": ["source=moe"] for name in ("moe", "moe_thesis")},
    **{f"world_model={name}": ["source=pce"] for name in ("pce", "pce_sparse", "pce_thesis")},
}
# Sub-folders of a group that are not options of it: world_model=moe reads world_model/robot/<robot>.yaml,
# world_model=pce world_model/pce_env/<env>.yaml.
NOT_OPTIONS = {"world_model/robot", "world_model/pce_env"}


def composed(overrides, hydra_config=False):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra_config)


def every_option() -> list[str]:
    options = []
    for group in sorted(path for path in CONF.iterdir() if path.is_dir()):
        for yaml in sorted(group.rglob("*.yaml")):
            if yaml.parent.relative_to(CONF).as_posix() in NOT_OPTIONS:
                continue
            options.append(f"{group.name}={yaml.relative_to(group).with_suffix('').as_posix()}")
    return options


def test_every_group_of_conf_is_listed_with_its_options():
    groups = {option.split("=")[0] for option in every_option()}
    assert groups == {"algo", "design", "env", "imagination", "logger", "policy", "robot", "source", "world_model"}
    assert set(COMPANIONS) <= set(every_option())  # a companion for an option that went is stale


@pytest.mark.parametrize("option", every_option())
def test_every_option_composes_and_passes_validation(option):
    # imagination=<x> without a model source is read by nothing: try it where it runs.
    companions = COMPANIONS.get(option, ["source=moe"] if option.startswith("imagination=") else [])
    cfg = composed([*companions, option])
    validate_config(cfg)


def test_robot_grammar_alone_selects_its_token_policy_and_a_flat_one_is_still_refused():
    cfg = composed(["robot=grammar"], hydra_config=True)
    assert cfg.policy.name == "token_modular" == cfg.hydra.runtime.choices.policy
    validate_config(composed([*GRAMMAR]))
    assert composed(["robot=grammar", "policy=token_mlp"]).policy.name == "token_mlp"  # the user's choice wins
    assert composed([]).policy.name == "mlp"  # the vertebrate keeps its flat policy
    with pytest.raises(ValueError, match="use a token policy"):
        validate_config(composed([*GRAMMAR, "policy=mlp"]))


@pytest.mark.parametrize("algo", ["sac", "crossq", "redq"])
@pytest.mark.parametrize("source", ["moe", "pce"])
def test_an_off_policy_learner_on_a_model_source_alone_trains_as_mbpo(algo, source):
    cfg = composed([f"source={source}", f"algo={algo}"], hydra_config=True)
    assert cfg.hydra.runtime.choices.imagination == "mbpo"
    validate_config(cfg)


def test_an_on_policy_learner_keeps_its_world_model_s_imagination_and_a_chosen_one_wins():
    assert composed(["source=moe"], hydra_config=True).hydra.runtime.choices.imagination == "recent_branch"
    assert composed(["source=pce"], hydra_config=True).hydra.runtime.choices.imagination == "short_branch"
    chosen = composed(["source=moe", "algo=sac", "imagination=branch"], hydra_config=True)
    assert chosen.hydra.runtime.choices.imagination == "branch"
    with pytest.raises(ValueError, match="imagination=mbpo"):  # and validation says which one runs
        validate_config(chosen)
