"""The package's import contract, checked in a fresh interpreter (the test process has imported everything)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path


def test_import_unipolicy_rl_registers_the_walker_env_id():
    script = textwrap.dedent(
        """
        import gymnasium
        assert "unipolicy_rl/Walker-v0" not in gymnasium.registry
        import unipolicy_rl
        env = gymnasium.make("unipolicy_rl/Walker-v0")
        observation, _ = env.reset(seed=0)
        assert env.observation_space.contains(observation)
        env.close()
        print("made", unipolicy_rl.ENV_ID)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "made unipolicy_rl/Walker-v0" in result.stdout


TRAINING_STACK = ("unipolicy_rl.collectors", "unipolicy_rl.world_models", "unipolicy_rl.learners",
                  "unipolicy_rl.objectives", "unipolicy_rl.factories", "torchrl.collectors")


def test_loading_and_evaluating_a_policy_imports_no_training_stack(tmp_path):
    """A policy is loaded, acts and is evaluated by ``python -m unipolicy_rl.evaluate`` without a collector,
    world model, learner or trainer in ``sys.modules``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from unipolicy_rl.checkpoint import RunCheckpoints
    from unipolicy_rl.factories import make_learner

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(str(root / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["robot.episode_length=5"])
    learner = make_learner(cfg, 18, 4)
    collector = _OneEpoch()
    config = OmegaConf.to_container(cfg, resolve=False)
    config.pop("run_name")  # resolved by Hydra in a run; not needed to load a policy
    checkpoints = RunCheckpoints(tmp_path, config=config, observation_dim=18, action_dim=4, learner=learner,
                                 collector=collector)
    path = checkpoints.save_best({"epoch": 1, "grid_mean": 0.0, "grid_min": 0.0})
    script = textwrap.dedent(
        f"""
        import sys
        from unipolicy_rl.checkpoint import load_policy
        from unipolicy_rl.evaluate import main
        policy = load_policy({str(path)!r})
        assert policy.act([0.0] * 18).shape == (4,)
        main([{str(path)!r}, "--grid", "1", "--out", {str(tmp_path / "evaluation")!r}])
        heavy = sorted(name for name in sys.modules if name.startswith({TRAINING_STACK!r}))
        print("training stack:", heavy)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "training stack: []" in result.stdout
    assert (tmp_path / "evaluation" / "designs.csv").is_file()


class _OneEpoch:
    """What a checkpoint reads of the real collector."""

    epoch = 1

    def state_dict(self) -> dict:
        return {"epoch": 1, "real_env_steps": 0}


# The layers below the builders: they take typed settings, never Hydra's config (docs/architecture.md).
BELOW_THE_BUILDERS = ("envs", "robots", "world_models", "polynomial_chaos", "collectors", "learners", "objectives",
                      "evaluation", "training", "cpu_speed", "uq")


def test_the_layers_below_the_builders_read_no_hydra_config():
    package = Path(__file__).resolve().parents[1] / "unipolicy_rl"
    readers = [str(path.relative_to(package)) for layer in BELOW_THE_BUILDERS
               for path in sorted((package / layer).rglob("*.py"))
               if any(line.lstrip().startswith(("import omegaconf", "from omegaconf", "import hydra", "from hydra"))
                      for line in path.read_text().splitlines())]
    assert readers == []
