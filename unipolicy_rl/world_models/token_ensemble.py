"""A probabilistic ensemble conditioned on the morphology: link tokens in, per-token state change out.

The flat :class:`~unipolicy_rl.world_models.GaussianEnsemble` reads one robot's state vector, so
its input size is tied to one topology. Robots of the grammar differ in how many links they have
and how those are joined, so :class:`TokenEnsemble` reads what the policy reads: one token per
link (:mod:`unipolicy_rl.envs.tokens`), and predicts each real token's change in its moving
features (position, velocity, orientation, angular velocity, joint angle and rate) as a Gaussian,
as PETS/MBPO predict a state's change. One network per member serves every token of every robot:

* each token's input is its own features (the root's x, y, which only say where the robot has
  walked to, left out, as the flat model leaves them out), a flag for the root, the action of its
  parent joint (0 where the joint is not driven) and the design (l, rho); the link's kind, size,
  hinge axis and joint are in its features, so the body is known to the network through them;
* an encoder embeds every token; the context of a token is the mean embedding of the robot's
  real tokens and the root's embedding (a body summary, and the base every link's position is
  measured from); a head reads the token's embedding beside its context and outputs the mean and
  bounded log-variance of its change.

Padding never counts: it is left out of the body summary (so a token's prediction cannot depend
on how far its robot was padded), out of the loss and the validation error (each robot's is the
mean over its real tokens), out of the standardisers' statistics, and its prediction is no
change (padding stays zeros). The token mask travels through the trainer as the last input
column, which the input standardiser passes through untouched; it is the mask the tokens imply
(:func:`~unipolicy_rl.envs.tokens.real_tokens`), since a :class:`Dynamics` sees the state alone.
Members are vectorised as the flat ensemble's are (:class:`~unipolicy_rl.world_models.networks.EnsembleMLP`
over ``[members, rows, features]``), the tokens of a batch being its rows; columns beyond the
largest robot of a batch are trimmed before the networks run.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from unipolicy_rl.envs.link_tokens import MOVING, MOVING_SIZE
from unipolicy_rl.envs.tokens import FEATURE_INDEX, TOKEN_SIZE, driven_tokens, real_tokens
from unipolicy_rl.networks import ACTIVATIONS
from unipolicy_rl.world_models.ensemble import ProbabilisticEnsemble, run_members
from unipolicy_rl.world_models.networks import EnsembleLinear, EnsembleMLP
from unipolicy_rl.world_models.token_layout import TokenLayout

# Per token: its features, the root flag, its joint's action, the design (l, rho), then the mask.
TOKEN_INPUT_SIZE = TOKEN_SIZE + 1 + 1 + 2 + 1
ROOT_XY = [FEATURE_INDEX["x"], FEATURE_INDEX["y"]]


def used_slots(tokens: torch.Tensor) -> int:
    """How many leading token slots hold a real link in some robot of the batch (at least 1):
    the env fills a robot's slots from the first, so the columns after these are padding in every row."""
    real = real_tokens(tokens).reshape(-1, tokens.shape[-2]).any(0)
    return int(real.nonzero().max()) + 1 if real.any() else 1


def masked_token_mean(values: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """``[..., L] -> [...]``: the mean over each row's real tokens (padding's values, finite or
    not, count for nothing)."""
    total = torch.where(real, values, torch.zeros_like(values)).sum(-1)
    return total / real.sum(-1).clamp_min(1)


class TokenEnsembleNetwork(nn.Module):
    """Every member's token network: ``[members, rows, L, in + mask] -> [members, rows, L, out]``.

    An encoder (two layers) embeds each token; a token's context is the masked mean of its row's
    embeddings (the body) and the root's embedding; a head reads ``[embedding, body, root]``.
    The head's first layer is split in two, the token's part per token and the context's part
    once per row (the same for every token of a robot), which is most of the head's cost saved.
    Padding tokens run through the per-token layers too (packing the real ones measured slower
    on the CPU than the work it saves) and are masked after.
    """

    def __init__(self, members: int, in_features: int, out_features: int, embedding: int,
                 hidden: Sequence[int], activation: str) -> None:
        super().__init__()
        self.members = members
        self.encoder = EnsembleMLP(members, in_features, embedding, (embedding,), activation)
        self.activation = ACTIVATIONS[activation]()
        self.token_in = EnsembleLinear(members, embedding, hidden[0])
        self.context_in = EnsembleLinear(members, 2 * embedding, hidden[0])
        self.head = EnsembleMLP(members, hidden[0], out_features, tuple(hidden[1:]), activation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows, links = x.shape[1], x.shape[2]
        real = x[..., -1:] > 0.5

        def per_token(layer: nn.Module, t: torch.Tensor) -> torch.Tensor:  # [members, rows * L, f]: the rows
            return layer(t.flatten(1, 2)).unflatten(1, (rows, links))

        embedded = self.activation(per_token(self.encoder, x[..., :-1]))
        embedded = torch.where(real, embedded, torch.zeros_like(embedded))
        body = embedded.sum(2) / real.sum(2).clamp_min(1)
        context = self.context_in(torch.cat([body, embedded[:, :, 0]], -1))  # [members, rows, hidden]
        return per_token(self.head, self.activation(per_token(self.token_in, embedded) + context.unsqueeze(2)))


class TokenEnsemble(ProbabilisticEnsemble):
    """Probabilistic ensemble of per-token state-change predictors for robots of any morphology.

    Args:
        layout: the tokens the model predicts (:class:`TokenLayout`: the env's ``max_links``).
        action_dim: the env's action slots, one per token (must be ``layout.max_links``).
        members, elites, min_log_var, max_log_var: as
            :class:`~unipolicy_rl.world_models.ensemble.ProbabilisticEnsemble` (the log-variance
            bounds are per moving feature, shared by every token).
        embedding: width of a token's embedding (and of the body summary and root context).
        hidden: the head's hidden layers.
        activation: of every layer.
    """

    def __init__(self, layout: TokenLayout, action_dim: int, members: int = 7, elites: int = 5,
                 embedding: int = 64, hidden: Sequence[int] = (128,), activation: str = "silu",
                 min_log_var: float = -10.0, max_log_var: float = 0.5, learn: Sequence[str] = (),
                 target: str = "change") -> None:
        if learn:  # (moe.yaml's `learn` and `target` reach this model too: robot=grammar's world model lays over it)
            raise ValueError(f"world_model.model.learn must be empty for TokenEnsemble: a grammar robot's reward and "
                             f"termination are known, got {list(learn)!r}")
        if target != "change":
            raise ValueError(f"world_model.model.target must be change for TokenEnsemble: it predicts each link "
                             f"token's change, got {target!r}")
        if not isinstance(layout, TokenLayout):
            raise ValueError(f"TokenEnsemble predicts link tokens: its layout must be a TokenLayout (robot=grammar), "
                             f"got {type(layout).__name__}")
        if action_dim != layout.max_links:
            raise ValueError(f"action_dim must be the env's {layout.max_links} token slots (one action per token), "
                             f"got {action_dim!r}")
        if isinstance(embedding, bool) or not (isinstance(embedding, int) and embedding >= 1):
            raise ValueError(f"embedding must be a positive integer, got {embedding!r}")
        if not hidden or not all(isinstance(size, int) and not isinstance(size, bool) and size >= 1
                                 for size in hidden):
            raise ValueError(f"hidden must be a non-empty list of positive integers (the head's layers), "
                             f"got {hidden!r}")
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(ACTIVATIONS)}")
        super().__init__(layout, TOKEN_INPUT_SIZE, MOVING_SIZE, members, elites, min_log_var, max_log_var)
        self.network = TokenEnsembleNetwork(members, TOKEN_INPUT_SIZE - 1, 2 * MOVING_SIZE, embedding, hidden,
                                            activation)

    # -- what the trainer calls -----------------------------------------------------------
    def inputs(self, state, action, design):
        """``[N, L', TOKEN_INPUT_SIZE]`` for the ``L'`` slots some robot of the batch uses; the last
        column is the token mask."""
        tokens = self.layout.tokens(state)
        used = used_slots(tokens)
        tokens = tokens[..., :used, :]
        features = tokens.clone()
        features[..., 0, ROOT_XY] = 0.0  # where the robot has walked to says nothing of its motion
        root = torch.zeros_like(tokens[..., :1])
        root[..., 0, :] = 1.0
        driven = driven_tokens(tokens).unsqueeze(-1)
        # Slots whose joint is not driven may hold anything (NaN too): they act on nothing.
        joint_action = self.layout.scaled_action(action[..., :used].unsqueeze(-1))
        joint_action = torch.where(driven, joint_action, torch.zeros_like(root))
        link_design = design.to(tokens.dtype).unsqueeze(-2).expand(*tokens.shape[:-1], 2)
        real = real_tokens(tokens).unsqueeze(-1).to(tokens.dtype)
        return torch.cat([features, root, joint_action, link_design, real], dim=-1)

    def targets(self, state, next_state):
        """``[N, L', MOVING_SIZE]``: each token's change in its moving features (the slots of :meth:`inputs`)."""
        tokens, next_tokens = self.layout.tokens(state), self.layout.tokens(next_state)
        used = used_slots(tokens)
        return next_tokens[..., :used, MOVING] - tokens[..., :used, MOVING]

    def fit_normalizers(self, inputs, targets):
        # Statistics of real tokens only; the mask column passes through (mean 0, scale 1).
        real = inputs[..., -1] > 0.5
        self.input_norm.fit(inputs[real])
        self.input_norm.mean[-1] = 0.0
        self.input_norm.std[-1] = 1.0
        self.target_norm.fit(targets[real])

    def training_loss(self, x, y):
        mean, log_var = self.mean_and_log_var(self.network(x))
        return masked_token_mean(self.gaussian_nll(mean, log_var, y).mean(-1), x[..., -1] > 0.5)

    @torch.no_grad()
    def validation_error(self, x, y):
        mean, _ = self.mean_and_log_var(self.network(x))
        return masked_token_mean(((mean - y) ** 2).mean(-1), x[..., -1] > 0.5)

    # -- the Dynamics interface ---------------------------------------------------------
    @torch.no_grad()
    def predict(self, state, action, design, member, deterministic=False):
        shape = state.shape
        state = state.reshape(-1, self.layout.size)
        x = self.input_norm(self.inputs(state, action.reshape(state.shape[0], -1), design.reshape(-1, 2)))
        used = x.shape[-2]
        mean, log_var = self.mean_and_log_var(run_members(self.network, x, member))
        change = self.target_norm.inverse(self.sample_change(mean, log_var, deterministic))
        change = torch.where(x[..., -1:] > 0.5, change, torch.zeros_like(change))  # padding stays zeros
        tokens = self.layout.tokens(state).clone()
        tokens[:, :used, MOVING] += change
        return tokens.flatten(-2).reshape(shape)
