"""Does a run's critic foresee how its policy's episode goes? Its value beside the return to go.

    python study/gym/critic_along_episode.py ../gym_runs/hopper-me-trpo/seed0/checkpoint.pt
    python study/gym/critic_along_episode.py CKPT --seed 3 --every 20

Plays one episode of the checkpoint's gymnasium task with its deterministic policy and prints, every
``--every`` steps, the critic's state value beside the discounted return that actually followed
(the learner's own gamma) and the step's reward. A critic within a few percent of the return to go
knows where the episode ends: a policy that still ends it early is then held by its optimiser (an
entropy that collapsed, a local optimum), not blind to the end. For an on-policy learner's run
(``algo=trpo|ppo``: a state-value critic) on ``env=gym``.
"""

from __future__ import annotations

import argparse

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.checkpoint import load_checkpoint, load_policy
from unipolicy_rl.env_factories import env_kind
from unipolicy_rl.envs.gym_task import GYM
from unipolicy_rl.policy import make_actor_critic


def values_and_returns(path: str, seed: int) -> tuple[list[float], list[float], list[float], bool]:
    """Along one deterministic episode: the critic's values, the discounted returns to go, the
    rewards, and whether the episode terminated (rather than ran out of time)."""
    state = load_checkpoint(path)
    cfg = OmegaConf.create(state["config"])
    if env_kind(cfg) != GYM or "critic" not in state.get("learner", {}):
        raise ValueError(f"{path}: not an on-policy learner's run on env=gym (algo=trpo|ppo); this reads its "
                         "state-value critic")
    _, critic = make_actor_critic(cfg, state["observation_dim"], state["action_dim"])
    critic.load_state_dict(state["learner"]["critic"])
    loaded = load_policy(path)
    normalizer = loaded.policy.module[0]  # the policy's own observation normaliser, which the critic reads too
    env = loaded.env_class(1, **loaded.env_kwargs)
    env.set_seed(seed)
    step = env.reset()
    values, rewards = [], []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        while True:
            values.append(float(critic(normalizer(TensorDict({"observation": step["observation"]})))["state_value"]))
            step = env.step(loaded.policy(step))
            rewards.append(float(step["next", "reward"]))
            if bool(step["next", "done"]):
                terminated = bool(step["next", "terminated"])
                break
            step = step["next"]
    env.close()
    gamma, to_go, returns = float(cfg.algo.gamma), 0.0, []
    for reward in reversed(rewards):
        to_go = reward + gamma * to_go
        returns.append(to_go)
    return values, returns[::-1], rewards, terminated


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="a run's checkpoint.pt (env=gym, algo=trpo|ppo)")
    parser.add_argument("--seed", type=int, default=0, help="the episode's reset seed")
    parser.add_argument("--every", type=int, default=10, help="print every this many steps")
    args = parser.parse_args(argv)
    values, returns, rewards, terminated = values_and_returns(args.checkpoint, args.seed)
    print(f"{'step':>5} {'value':>8} {'return to go':>13} {'value/return':>13} {'reward':>7}")
    last = len(values) - 1
    for t in [*range(0, last, args.every), last]:
        ratio = values[t] / returns[t] if returns[t] else float("nan")
        print(f"{t:>5} {values[t]:>8.1f} {returns[t]:>13.1f} {ratio:>13.2f} {rewards[t]:>7.2f}")
    print(f"{len(values)} steps, return {sum(rewards):.1f}, " + ("terminated" if terminated else "ran out of time"))


if __name__ == "__main__":
    main()
