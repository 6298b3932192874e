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
           ["source=pce", "world_model=pce_thesis"])
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


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("epochs=-1", "epochs must be an integer >= 1, got -1"),
        ("algo.gamma=1.5", "algo.gamma must lie in (0, 1], got 1.5"),
        ("evaluation.grid=0", "evaluation.grid must be an integer >= 1, got 0"),
    ],
)
def test_a_bad_override_stops_train_py_before_any_robot_is_built(tmp_path, override, message):
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), override, f"hydra.run.dir={tmp_path}"],
                            cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode != 0
    assert message in result.stderr
    assert not (tmp_path / "metrics.csv").exists()
