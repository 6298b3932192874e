"""The package's import contract, checked in a fresh interpreter (the test process has imported everything)."""

from __future__ import annotations

import subprocess
import sys
import textwrap


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
