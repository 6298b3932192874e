"""Time one TRPO update of the token policies: the transformer (full and body-graph attention)
against the padded-MLP baseline, on the same batch of padded link tokens.

A batch of ``--samples`` synthetic steps (episodes of 100) of robots of two morphologies padded
to ``--tokens`` tokens of ``--features`` features (no env: the cost is the networks'); the
settings of ``conf/algo/trpo.yaml`` and ``conf/policy/``: 10 CG iterations, max KL 0.01, critic
Adam for 10 epochs of minibatches of 128. Per architecture and ``fisher_fraction`` (the share of
the batch the Fisher-vector products use, ``--fractions``), one warm-up update, then
``--repeats`` timed ones, the variants alternating so load from other processes hits each
alike. Printed: the median wall time of the policy step (``natural_gradient_step``: surrogate
gradient, CG with Fisher-vector products, line search) and of the whole update (GAE, policy
step, critic fit), each fraction's step time as a ratio of the whole batch's, and whether every
step kept the trust region: accepted steps, and the largest whole-batch KL over ``max_kl``. One
thread.

    python benchmarks/token_policy_update.py                 # 1,000 steps, 12 tokens, 3 repeats
    python benchmarks/token_policy_update.py --architectures token_transformer --fractions 1.0 0.2
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.envs.tokens import ACTION_MASK, TOKEN_MASK, TOKEN_PARENT, TOKENS
from unipolicy_rl.objectives import TRPOLoss, TRPOStepResult, TRPOUpdater, TrustRegion, natural_gradient_step
from unipolicy_rl.token_networks import (
    TokenTransformerSettings,
    make_padded_mlp_actor,
    make_padded_mlp_critic,
    make_token_transformer_actor,
    make_token_transformer_critic,
)

EPISODE_LENGTH = 100
# Two morphologies: parents per real link (-1 the root); a 7-link quadruped and an 11-link hexapod.
ROBOTS = ([-1, 0, 0, 0, 0, 1, 2], [-1, 0, 0, 0, 0, 0, 0, 1, 2, 3, 4])


def token_batch(samples: int, tokens: int, features: int) -> TensorDict:
    """``[samples // 100, 100]`` steps, robots alternating by episode, with random features."""
    envs = samples // EPISODE_LENGTH
    parent = torch.full((envs, EPISODE_LENGTH, tokens), -1, dtype=torch.int64)
    for env in range(envs):
        parents = ROBOTS[env % len(ROBOTS)]
        parent[env, :, : len(parents)] = torch.tensor(parents)
    mask = torch.zeros(envs, EPISODE_LENGTH, tokens, dtype=torch.bool)
    for env in range(envs):
        mask[env, :, : len(ROBOTS[env % len(ROBOTS)])] = True
    done = torch.zeros(envs, EPISODE_LENGTH, 1, dtype=torch.bool)
    done[:, -1] = True

    def observation():
        return {TOKENS: torch.randn(envs, EPISODE_LENGTH, tokens, features), TOKEN_MASK: mask, TOKEN_PARENT: parent}

    return TensorDict({**observation(), ACTION_MASK: mask & (parent >= 0),
                       "next": TensorDict({**observation(), "reward": torch.randn(envs, EPISODE_LENGTH, 1),
                                           "done": done, "terminated": done.clone()}, [envs, EPISODE_LENGTH])},
                      [envs, EPISODE_LENGTH])


def architectures(tokens: int, features: int) -> dict[str, tuple]:
    transformer = TokenTransformerSettings()
    graph = TokenTransformerSettings(graph_attention=True)
    return {
        "token_transformer": (make_token_transformer_actor(features, transformer, -0.5),
                              make_token_transformer_critic(features, transformer)),
        "token_transformer graph": (make_token_transformer_actor(features, graph, -0.5),
                                    make_token_transformer_critic(features, graph)),
        "token_mlp": (make_padded_mlp_actor(features, tokens, (64, 64), "tanh", -0.5),
                      make_padded_mlp_critic(features, tokens, (64, 64), "tanh")),
    }


def timed_update(updater: TRPOUpdater, batch: TensorDict) -> tuple[float, float, TRPOStepResult]:
    """(policy step seconds, whole update seconds, the step's result) on fresh copies of ``batch``."""
    loss = updater.loss_module
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = loss.actor_network(batch.clone())  # actions and behaviour loc/scale of this policy
    step_batch = batch.clone()
    loss.compute_advantage(step_batch)
    flat = step_batch.reshape(-1)
    advantage = loss.advantage(flat)
    state = {name: param.detach().clone() for name, param in loss.actor_network_params.items(True, True)}
    start = time.perf_counter()
    result = natural_gradient_step(loss, flat, advantage=advantage, trust_region=updater.trust_region)
    step_seconds = time.perf_counter() - start
    with torch.no_grad():  # back to the behaviour policy before the whole update
        for name, param in loss.actor_network_params.items(True, True):
            param.copy_(state[name])
    start = time.perf_counter()
    updater.update(batch)
    return step_seconds, time.perf_counter() - start, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--tokens", type=int, default=12)
    parser.add_argument("--features", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fractions", type=float, nargs="+", default=[1.0],
                        help="fisher_fraction values to time (default 1.0: the whole batch)")
    parser.add_argument("--architectures", nargs="+", default=None, help="a subset of the architectures")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    chosen = architectures(args.tokens, args.features)
    names = args.architectures or list(chosen)
    updaters = {}
    for name in names:
        for fraction in args.fractions:
            actor, critic = copy.deepcopy(chosen[name])  # every fraction starts from the same networks
            updaters[name, fraction] = TRPOUpdater(TRPOLoss(actor, critic), trust_region=TrustRegion(
                fisher_fraction=fraction), generator=torch.Generator().manual_seed(0))
    times: dict[tuple[str, float], list[tuple[float, float, TRPOStepResult]]] = {key: [] for key in updaters}
    for repeat in range(args.repeats + 1):
        batch = token_batch(args.samples, args.tokens, args.features)
        for key, updater in updaters.items():
            result = timed_update(updater, batch)
            if repeat:  # the first is a warm-up
                times[key].append(result)
    print(f"{args.samples} steps, {args.tokens} tokens of {args.features} features, median of {args.repeats}:")
    max_kl = TrustRegion().max_kl
    for (name, fraction), results in times.items():
        parameters = sum(p.numel() for p in updaters[name, fraction].loss_module.actor_parameters())
        step = statistics.median(result[0] for result in results)
        update = statistics.median(result[1] for result in results)
        whole = statistics.median(result[0] for result in times[name, args.fractions[0]])
        accepted = sum(result[2].accepted for result in results)
        worst_kl = max(result[2].kl for result in results)
        tries = statistics.mean(result[2].line_search_tries for result in results)
        print(f"  {name:24s} fisher_fraction {fraction:4.2f}  actor parameters {parameters:6d}  policy step "
              f"{step:6.2f} s ({step / whole:4.2f} of fraction {args.fractions[0]:g})  whole update {update:6.2f} s  "
              f"accepted {accepted}/{len(results)}, max KL {worst_kl / max_kl:4.2f} x max_kl, "
              f"line-search tries {tries:.1f}")


if __name__ == "__main__":
    main()
