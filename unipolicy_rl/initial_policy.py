"""Starting a new run from another run's policy (``init_policy``): e.g. TRPO fine-tuning a policy
that ``algo=distill`` taught.

Only the policy moves over (the actor's weights, its Gaussian's std among them, and the
observation normaliser's statistics): the critic, the optimisers and the run's counters start
fresh, as they would for any new run. The learner's own observation statistics start empty, so
its first refresh (``normalizer_refresh: preserve``) re-expresses the loaded policy's first
layers for this run's observations without changing what it does.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

# The settings a policy's weights are built for: a run starting from another run's policy must
# share them (the learner may differ where its actor is the same network: distill, TRPO, PPO).
POLICY_SETTINGS = ("robot.kind", "policy.name", "policy.network", "algo.actor_hidden", "algo.activation")


def policy_to_start_from(cfg: DictConfig, path: str | Path, observation_dim: int, action_dim: int) -> dict:
    """The policy state (:meth:`~unipolicy_rl.learners.Learner.policy_state`'s layout) saved at
    ``path``, checked to fit this run: the same policy settings (:data:`POLICY_SETTINGS`), the
    same observation and action sizes, and for ``robot=grammar`` the same env settings its tokens
    depend on (padding, layout, tokens, physics).

    Raises:
        ValueError: naming ``init_policy``, the file and every setting that differs.
    """
    from unipolicy_rl.checkpoint import load_checkpoint  # (checkpoint imports the policy stack)
    from unipolicy_rl.env_factories import env_builder
    from unipolicy_rl.learners.distillation import differing_env_settings

    try:
        state = load_checkpoint(path)
    except (FileNotFoundError, ValueError) as error:
        raise ValueError(f"init_policy: {error}") from None
    saved = OmegaConf.create(state["config"])
    differences = []
    for key in POLICY_SETTINGS:
        ours, theirs = OmegaConf.select(cfg, key, default=None), OmegaConf.select(saved, key, default=None)
        if ours != theirs:
            differences.append(f"{key}: {_show(ours)} here, {_show(theirs)} there")
    sizes, saved_sizes = (observation_dim, action_dim), (state["observation_dim"], state["action_dim"])
    if sizes != saved_sizes:
        differences.append(f"observation and action sizes: {sizes} here, {saved_sizes} there")
    if not differences and OmegaConf.select(cfg, "robot.kind") == "grammar":
        ours_env, theirs_env = env_builder(cfg)[1], env_builder(saved)[1]
        differences += [f"robot's {key}: {ours_env.get(key)!r} here, {theirs_env.get(key)!r} there"
                        for key in differing_env_settings(ours_env, theirs_env)]
    if differences:
        raise ValueError(f"init_policy: the policy in {str(path)!r} does not fit this run (" + "; ".join(differences)
                         + "): start from a policy trained with this run's policy and robot settings")
    return state["policy"]


def _show(value) -> str:
    return str(OmegaConf.to_container(value) if OmegaConf.is_config(value) else value)
