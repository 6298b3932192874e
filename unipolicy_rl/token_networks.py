"""Policy and value networks that read a robot of any morphology as padded link tokens.

The input is the contract of :mod:`unipolicy_rl.envs.tokens`: ``TOKENS`` ``[*, L, F]`` (here
normalised), ``TOKEN_MASK`` ``[*, L]`` and ``TOKEN_PARENT`` ``[*, L]``; the action is ``[*, L]``,
slot ``i`` driving link ``i``'s parent joint, restricted to ``ACTION_MASK``.

Three architectures with one interface (``loc``/``scale`` per slot, the same distribution and
critic output):

* the token transformer (Amorpheus / MetaMorph): a linear embedding per token, a few
  self-attention layers in which no real token sees padding, one shared action head applied to
  every token. With ``graph_attention`` each token attends only to itself, its parent and its
  children (the Body Transformer's masked attention), so information travels one link per layer.
  Its weights do not depend on ``L`` (unless ``slot_embedding`` adds a learnt vector per slot):
  the same network runs any robot, and padding a robot with empty tokens leaves its real slots'
  outputs unchanged;
* the padded MLP (the baseline): the normalised tokens flattened in slot order (padding zero)
  with the token mask beside them, through an MLP to ``[L]`` means; its weights are tied to ``L``;
* the modular policy: one controller shared by every joint (an MLP encoding per token, one head
  MLP per joint on its token, its parent's and children's encodings and the body's pooled
  encoding); like the transformer's, its weights do not depend on ``L`` or on the slot order.

Three critics (state value, ``[*, 1]``), any of them beside either actor: the transformer's own
encoder, mean-pooled over the real tokens; the padded MLP; and the pooled token MLP (Deep Sets:
one MLP applied to every token, the masked mean and max over real tokens, an MLP head), whose
cost is a per-token MLP instead of attention layers and whose weights, like the transformer's,
do not depend on ``L``.

The std is one shared, state-independent parameter (``exp(log_std)`` on every slot). A vector
per slot has no fixed meaning when slot 3 is a leg joint on one robot and a body joint on the
next, and its size would tie the policy to ``L``; a std per joint kind would need the kind as a
key of its own (today it is only somewhere among the token features). One scalar keeps the
parameter vector, and so the TRPO step, independent of the padding.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, ValueOperator

from unipolicy_rl.envs.tokens import ACTION_MASK, CLOCK, TOKEN_MASK, TOKEN_PARENT, TOKENS
from unipolicy_rl.masked_normal import MaskedIndependentNormal
from unipolicy_rl.networks import ACTIVATIONS, _orthogonal_linear, make_mlp
from unipolicy_rl.observation_statistics import reexpress_linear, reexpress_weights

__all__ = [
    "TRANSFORMER_ACTIVATIONS",
    "PaddedTokenMLP",
    "SharedLogStd",
    "TokenEncoder",
    "TokenTransformerSettings",
    "attention_blocked",
    "make_modular_actor",
    "make_padded_mlp_actor",
    "make_padded_mlp_critic",
    "make_pooled_token_critic",
    "make_token_transformer_actor",
    "make_token_transformer_critic",
    "used_slots",
]

TRANSFORMER_ACTIVATIONS = ("relu", "gelu")
CLOCK_SIZE = 2  # the env's CLOCK: (sin, cos) of the gait phase


@dataclass(frozen=True)
class TokenTransformerSettings:
    """The token transformer's sizes (``conf/policy/token_transformer.yaml``); small enough for a CPU.

    Attributes:
        d_model: width of a token's embedding and of every attention layer.
        heads: attention heads per layer (must divide ``d_model``).
        layers: self-attention layers (at least one; with ``graph_attention`` also the number
            of links information can travel).
        feedforward: hidden width of each layer's per-token feed-forward block.
        activation: the feed-forward block's non-linearity (``relu`` or ``gelu``).
        graph_attention: restrict attention to a token's parent, children and itself (Body
            Transformer); False attends to every real token (MetaMorph).
        slot_embedding: add a learnt vector per slot to each token's embedding (MetaMorph's
            position embedding over the link order). Without it the one shared action head can
            tell two joints apart only by their features, and mirrored legs of one body differ in
            little but the sign of a position; with it each slot can act on its own, as the
            padded MLP's per-slot outputs do. It ties the weights to the padding length
            (``max_tokens``), as MetaMorph's does; False keeps them free of it.
        head_hidden: hidden widths of the per-token action head (tanh between them, as the
            padded MLP's); empty: one linear map from a token's encoding to its action mean.
        head_reads_token: the action head reads the token's own normalised features beside its
            encoding. The encoding has passed LayerNorms and attention, so a joint's own angle
            and rate reach its action only through them; the skip gives each joint the direct,
            local path an MLP has, with attention left to add what other links know.
    """

    d_model: int = 64
    heads: int = 2
    layers: int = 2
    feedforward: int = 128
    activation: str = "relu"
    graph_attention: bool = False
    slot_embedding: bool = False
    head_hidden: tuple[int, ...] = ()
    head_reads_token: bool = False

    def __post_init__(self) -> None:
        # Hydra hands a list; a tuple keeps the settings hashable and comparable.
        object.__setattr__(self, "head_hidden", tuple(self.head_hidden))
        for width in self.head_hidden:
            if not (isinstance(width, int) and not isinstance(width, bool) and width >= 1):
                raise ValueError(f"head_hidden must hold positive integers, got {list(self.head_hidden)!r}")
        for name in ("d_model", "heads", "layers", "feedforward"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.d_model % self.heads:
            raise ValueError(f"d_model={self.d_model} must be divisible by heads={self.heads}")
        if self.activation not in TRANSFORMER_ACTIVATIONS:
            raise ValueError(f"activation must be one of {TRANSFORMER_ACTIVATIONS}, got {self.activation!r}")
        for name in ("graph_attention", "slot_embedding", "head_reads_token"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")


def attention_blocked(token_mask: torch.Tensor, token_parent: torch.Tensor, graph: bool) -> torch.Tensor:
    """``[B, L, L]`` bool, True where query token ``q`` may NOT attend to key token ``k``.

    Padding keys are blocked for every query, so a real token's output never depends on
    padding. With ``graph``, keys other than the query's parent and children are blocked too.
    A token may always attend to itself: a padding query (or a root whose neighbours are all
    padding) then has one key left instead of an all-blocked row, whose softmax is NaN.
    """
    length = token_mask.shape[-1]
    index = torch.arange(length, device=token_mask.device)
    allowed = token_mask.unsqueeze(-2).expand(*token_mask.shape[:-1], length, length)
    if graph:
        is_parent = token_parent.unsqueeze(-1) == index  # [B, q, k]: k is q's parent
        allowed = allowed & (is_parent | is_parent.transpose(-1, -2))
    return ~(allowed | torch.eye(length, dtype=torch.bool, device=token_mask.device))


def used_slots(token_mask: torch.Tensor) -> int:
    """One past the last slot that any robot of ``token_mask`` ``[B, L]`` uses (at least 1)."""
    used = token_mask.any(0).nonzero()
    return int(used[-1]) + 1 if len(used) else 1


class TokenEncoder(nn.Module):
    """``(tokens [*, L, F], mask, parent) -> [*, L, d_model]``: embedding (plus a learnt vector per
    slot with ``settings.slot_embedding``, for up to ``max_tokens`` slots), then self-attention layers."""

    def __init__(self, token_features: int, settings: TokenTransformerSettings, max_tokens: int | None = None) -> None:
        super().__init__()
        if not (isinstance(token_features, int) and token_features >= 1):
            raise ValueError(f"token_features must be a positive integer, got {token_features!r}")
        self.settings = settings
        self.embedding = nn.Linear(token_features, settings.d_model)
        self.slot_embedding = None
        if settings.slot_embedding:
            if not (isinstance(max_tokens, int) and max_tokens >= 1):
                raise ValueError(f"slot_embedding needs the padding length max_tokens (a positive integer), "
                                 f"got {max_tokens!r}")
            # Zeros: the network starts as the one without slot vectors; each slot's vector then
            # learns from the gradient at its slot alone.
            self.slot_embedding = nn.Parameter(torch.zeros(max_tokens, settings.d_model))
        layer = nn.TransformerEncoderLayer(settings.d_model, settings.heads, settings.feedforward, dropout=0.0,
                                           activation=settings.activation, batch_first=True, norm_first=True)
        # Dropout 0: TRPO's ratio, KL and line search need one deterministic policy.
        self.encoder = nn.TransformerEncoder(layer, settings.layers, norm=nn.LayerNorm(settings.d_model),
                                             enable_nested_tensor=False)

    def forward(self, tokens: torch.Tensor, token_mask: torch.Tensor, token_parent: torch.Tensor) -> torch.Tensor:
        """The encoded tokens; slots past the last one any robot of the batch uses come out as zeros.

        Those trailing slots are padding for every robot, and no real token attends to padding,
        so they are cut before the layers: a batch of 20-link robots padded to 29 slots costs
        what 20 slots cost (attention is quadratic in the slots), with the real tokens' outputs
        unchanged. A padding slot's output is never read (the actions' mask, the critics' pooling).
        """
        batch_shape, (length, features) = tokens.shape[:-2], tokens.shape[-2:]
        if self.slot_embedding is not None and length > len(self.slot_embedding):
            raise ValueError(f"the slot embedding has {len(self.slot_embedding)} slots (max_tokens), "
                             f"got tokens of {length} slots")
        flat_mask = token_mask.reshape(-1, length)
        used = used_slots(flat_mask)
        flat_mask, flat_parent = flat_mask[:, :used], token_parent.reshape(-1, length)[:, :used]
        blocked = attention_blocked(flat_mask, flat_parent, self.settings.graph_attention)
        blocked = blocked.repeat_interleave(self.settings.heads, dim=0)  # [B * heads, L, L], as the encoder wants
        embedded = self.embedding(tokens.reshape(-1, length, features)[:, :used])
        if self.slot_embedding is not None:
            embedded = embedded + self.slot_embedding[:used]
        # The math kernel: TRPO's Fisher-vector product differentiates the network's backward
        # pass, and the fused CPU attention kernel has no double backward.
        with sdpa_kernel(SDPBackend.MATH):
            encoded = self.encoder(embedded, mask=blocked)
        if used < length:
            encoded = nn.functional.pad(encoded, (0, 0, 0, length - used))
        return encoded.reshape(*batch_shape, length, -1)

    def reexpress_input(self, old_loc, old_scale, new_loc, new_scale) -> None:
        """Re-express the embedding for a normaliser moved from ``(old_loc, old_scale)`` to the new
        statistics, so each real token's embedding, and every output, stays the same (padding
        tokens stay zero and are never seen by a real token)."""
        reexpress_linear(self.embedding, old_loc, old_scale, new_loc, new_scale)


class SharedLogStd(nn.Module):
    """``loc -> (loc, exp(log_std))``, one learnt log-std shared by every slot (see the module doc)."""

    def __init__(self, init_log_std: float = 0.0) -> None:
        super().__init__()
        self.log_std = nn.Parameter(torch.full((1,), float(init_log_std)))

    def forward(self, loc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return loc, self.log_std.exp().expand_as(loc)


class _TransformerActorNetwork(nn.Module):
    """Tokens -> per-slot ``loc`` (one action head shared by every token: a linear map or a small
    tanh MLP, on the token's encoding and, with ``head_reads_token``, its own features) and the
    shared std."""

    def __init__(self, token_features: int, settings: TokenTransformerSettings, init_log_std: float,
                 max_tokens: int | None) -> None:
        super().__init__()
        self.encoder = TokenEncoder(token_features, settings, max_tokens)
        self.reads_token = settings.head_reads_token
        head_inputs = settings.d_model + (token_features if self.reads_token else 0)
        # The token's features come first, so a normaliser refresh re-expresses the leading columns.
        head = make_mlp(head_inputs, 1, settings.head_hidden, "tanh", output_gain=0.01)  # loc starts near 0
        # A lone linear head stays a bare nn.Linear: the checkpoints written before heads had
        # hidden layers keep their parameter names.
        self.action_head = head[0] if len(head) == 1 else head
        self.std = SharedLogStd(init_log_std)

    def forward(self, tokens, token_mask, token_parent):
        encoded = self.encoder(tokens, token_mask, token_parent)
        if self.reads_token:  # padding rows zeroed: whatever they hold never reaches a gradient
            real = torch.where(token_mask.unsqueeze(-1), tokens, torch.zeros((), dtype=tokens.dtype))
            head_input = torch.cat([real, encoded], -1)
        else:
            head_input = encoded
        return self.std(self.action_head(head_input).squeeze(-1))

    def reexpress_input(self, old_loc, old_scale, new_loc, new_scale) -> None:
        """The embedding and, where the head reads the token, the head's token columns, for a
        moved normaliser: every real slot's action mean stays the same."""
        self.encoder.reexpress_input(old_loc, old_scale, new_loc, new_scale)
        if self.reads_token:
            first = self.action_head if isinstance(self.action_head, nn.Linear) else self.action_head[0]
            reexpress_weights(first.weight, first.bias, old_loc, old_scale, new_loc, new_scale)


def _masked_mean(values: torch.Tensor, token_mask: torch.Tensor) -> torch.Tensor:
    """``[*, L, D] -> [*, D]``: the mean over the real tokens (0 for a robot with none)."""
    real = token_mask.unsqueeze(-1).to(values.dtype)
    return (values * real).sum(-2) / real.sum(-2).clamp_min(1.0)


def _masked_max(values: torch.Tensor, token_mask: torch.Tensor) -> torch.Tensor:
    """``[*, L, D] -> [*, D]``: the largest value over the real tokens (0 for a robot with none)."""
    real = token_mask.unsqueeze(-1)
    lowest = torch.full((), float("-inf"), dtype=values.dtype, device=values.device)
    largest = torch.where(real, values, lowest).amax(-2)
    return torch.where(real.any(-2), largest, torch.zeros((), dtype=values.dtype, device=values.device))


class _TransformerCriticNetwork(nn.Module):
    """Tokens -> state value: the mean of the encoded real tokens, then a linear head."""

    def __init__(self, token_features: int, settings: TokenTransformerSettings, max_tokens: int | None) -> None:
        super().__init__()
        self.encoder = TokenEncoder(token_features, settings, max_tokens)
        self.value_head = _orthogonal_linear(settings.d_model, 1, gain=1.0)

    def forward(self, tokens, token_mask, token_parent):
        return self.value_head(_masked_mean(self.encoder(tokens, token_mask, token_parent), token_mask))


def per_token_encoder(token_features: int, hidden_sizes: tuple[int, ...], activation: str, owner: str) -> nn.Sequential:
    """One MLP applied to every token, ``[*, L, F] -> [*, L, hidden_sizes[-1]]``, each layer followed
    by the activation (its last layer is a hidden one: gain sqrt 2): the per-token half of the pooled
    critic and of the modular policy. ``owner`` names the network in the errors."""
    if not (isinstance(token_features, int) and token_features >= 1):
        raise ValueError(f"token_features must be a positive integer, got {token_features!r}")
    if not hidden_sizes:
        raise ValueError(f"{owner} needs at least one hidden size (the width of each token's encoding), "
                         "got hidden_sizes=()")
    # make_mlp checks the activation's name.
    layers = make_mlp(token_features, hidden_sizes[-1], hidden_sizes[:-1], activation, output_gain=math.sqrt(2.0))
    return nn.Sequential(*layers, ACTIVATIONS[activation]())


class PooledTokenCritic(nn.Module):
    """``(tokens [*, L, F], mask [*, L]) -> [*, 1]``, Deep Sets: one MLP on every token (its
    hidden layers ``hidden_sizes``, each followed by the activation), the masked mean and max of
    its outputs over the real tokens, then an MLP head (the same hidden sizes) to the value.

    The cheap critic for token policies: where the transformer's critic runs attention layers
    per token and pair of tokens, this runs one small MLP per token, and the tokens meet only in
    the pooling. Padding never reaches the value (its rows are zeroed before the MLP, so even a
    non-finite padding row has no gradient to leak, and both poolings skip it), and the weights
    do not depend on ``L``, so the same critic values any robot. The max keeps what a mean over
    a large robot would dilute (the one link that is falling, the fastest foot).
    """

    def __init__(self, token_features: int, hidden_sizes: Sequence[int] = (64, 64), activation: str = "tanh") -> None:
        super().__init__()
        hidden_sizes = tuple(hidden_sizes)
        self.token_mlp = per_token_encoder(token_features, hidden_sizes, activation, "the pooled critic")
        self.head = make_mlp(2 * hidden_sizes[-1], 1, hidden_sizes, activation, output_gain=1.0)

    def forward(self, tokens: torch.Tensor, token_mask: torch.Tensor) -> torch.Tensor:
        real = token_mask.unsqueeze(-1)
        per_token = self.token_mlp(torch.where(real, tokens, torch.zeros((), dtype=tokens.dtype)))
        return self.head(torch.cat([_masked_mean(per_token, token_mask), _masked_max(per_token, token_mask)], -1))

    def reexpress_input(self, old_loc, old_scale, new_loc, new_scale) -> None:
        """Re-express the per-token MLP's first layer for a moved normaliser: each real token's
        output, and so the value, stays the same (padding is zeroed and pooled out either way)."""
        reexpress_linear(self.token_mlp[0], old_loc, old_scale, new_loc, new_scale)


class PaddedTokenMLP(nn.Module):
    """``(tokens [*, L, F], mask [*, L]) -> [*, out]``: the flattened tokens (padding zeroed) and
    the mask as floats, through an MLP. The mask input lets the network tell a real token of
    zeros from padding, and lets a normaliser refresh be absorbed exactly (:meth:`reexpress_input`)."""

    def __init__(self, token_features: int, max_tokens: int, out_features: int, hidden_sizes: Sequence[int],
                 activation: str, output_gain: float) -> None:
        super().__init__()
        for name, value in (("token_features", token_features), ("max_tokens", max_tokens)):
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        self.token_features, self.max_tokens = token_features, max_tokens
        self.mlp = make_mlp(max_tokens * (token_features + 1), out_features, hidden_sizes, activation, output_gain)

    def forward(self, tokens: torch.Tensor, token_mask: torch.Tensor) -> torch.Tensor:
        if tokens.shape[-2:] != (self.max_tokens, self.token_features):
            raise ValueError(f"the padded MLP reads {self.max_tokens} tokens of {self.token_features} features, "
                             f"got tokens shaped {tuple(tokens.shape)}")
        real = token_mask.unsqueeze(-1)
        flat = torch.where(real, tokens, torch.zeros((), dtype=tokens.dtype)).flatten(-2)
        return self.mlp(torch.cat([flat, token_mask.to(tokens.dtype)], dim=-1))

    def reexpress_input(self, old_loc, old_scale, new_loc, new_scale) -> None:
        """The first layer for a moved normaliser, outputs unchanged: per token block
        ``W_l' = W_l diag(s1 / s0)``, and the shift ``W_l (m1 - m0) / s0`` goes to the mask
        input of slot ``l`` (it applies only where the token is real)."""
        layer = self.mlp[0]
        length, features = self.max_tokens, self.token_features
        with torch.no_grad():
            weight = layer.weight.double()
            token_weight = weight[:, : length * features].reshape(-1, length, features)
            shift = token_weight @ ((new_loc - old_loc) / old_scale).double()  # [out, L]
            token_weight = token_weight * (new_scale / old_scale).double()
            new_weight = torch.cat([token_weight.reshape(-1, length * features), weight[:, length * features:] + shift],
                                   dim=1)
            layer.weight.copy_(new_weight.to(layer.weight.dtype))


class _PaddedMLPActorNetwork(nn.Module):
    def __init__(self, token_features, max_tokens, hidden_sizes, activation, init_log_std) -> None:
        super().__init__()
        self.mlp = PaddedTokenMLP(token_features, max_tokens, max_tokens, hidden_sizes, activation, output_gain=0.01)
        self.std = SharedLogStd(init_log_std)

    def forward(self, tokens, token_mask):
        return self.std(self.mlp(tokens, token_mask))


class _ModularActorNetwork(nn.Module):
    """Tokens -> per-slot ``loc`` from one controller shared by every joint (Shared Modular
    Policies, NerveNet): each real token is encoded by one MLP (``hidden_sizes``), and each joint's
    mean comes from one head MLP (the same sizes) on its own token, its parent's encoding, the mean
    of its children's encodings and the whole body's masked mean and max of encodings.

    Why: the padded MLP ties its weights to slots, so a robot it never saw is read through
    weights that other bodies' parts trained; the transformer shares its weights across joints
    but learns slowly here. This network shares every weight across joints and robots, as the
    transformer does, at the cost of an MLP per token: a new body is read the way its parts were,
    one link away from each joint and through the body's summary beyond. Padding never reaches a
    real slot (it is zeroed, left out of both poolings, and no real link is its parent or child).

    With ``clock`` the head also reads the env's gait clock (``(sin, cos)`` of one phase for the
    whole body): a rhythm every joint shares, so one controller can make a travelling wave on any
    body (each joint's offset on the phase from what its token says), where without it the rhythm
    must come from the body's own feedback, which differs from body to body.
    """

    def __init__(self, token_features: int, hidden_sizes: Sequence[int], activation: str,
                 init_log_std: float, clock: bool = False) -> None:
        super().__init__()
        hidden_sizes = tuple(hidden_sizes)
        self.encoder = per_token_encoder(token_features, hidden_sizes, activation, "the modular policy")
        width = hidden_sizes[-1]
        self.clock = clock
        # The token's own features come first, so a normaliser refresh re-expresses the leading columns.
        self.head = make_mlp(token_features + 4 * width + (CLOCK_SIZE if clock else 0), 1, hidden_sizes, activation,
                             output_gain=0.01)
        self.std = SharedLogStd(init_log_std)

    def forward(self, tokens, token_mask, token_parent, clock=None):
        real = token_mask.unsqueeze(-1)
        tokens = torch.where(real, tokens, torch.zeros((), dtype=tokens.dtype))
        encoded = torch.where(real, self.encoder(tokens), torch.zeros((), dtype=tokens.dtype))  # [*, L, W]
        has_parent = ((token_parent >= 0) & token_mask).unsqueeze(-1)
        parent_index = token_parent.clamp(min=0).unsqueeze(-1).expand_as(encoded)
        parent = torch.where(has_parent, encoded.gather(-2, parent_index), torch.zeros((), dtype=tokens.dtype))
        # Each child's encoding added at its parent's slot (a root or padding child adds nothing).
        child_sum = torch.zeros_like(encoded).scatter_add(-2, parent_index, torch.where(has_parent, encoded, 0.0))
        child_count = torch.zeros_like(encoded[..., :1]).scatter_add(-2, parent_index[..., :1],
                                                                      has_parent.to(tokens.dtype))
        children = child_sum / child_count.clamp(min=1.0)
        body = torch.cat([_masked_mean(encoded, token_mask), _masked_max(encoded, token_mask)], -1)
        body = body.unsqueeze(-2).expand(*encoded.shape[:-1], body.shape[-1])
        inputs = [tokens, parent, children, body]
        if self.clock:
            inputs.append(clock.unsqueeze(-2).expand(*encoded.shape[:-1], clock.shape[-1]))
        return self.std(self.head(torch.cat(inputs, -1)).squeeze(-1))

    def reexpress_input(self, old_loc, old_scale, new_loc, new_scale) -> None:
        """The encoder's first layer and the head's token columns, for a moved normaliser: every
        real slot's action mean stays the same."""
        reexpress_linear(self.encoder[0], old_loc, old_scale, new_loc, new_scale)
        reexpress_weights(self.head[0].weight, self.head[0].bias, old_loc, old_scale, new_loc, new_scale)


def _gaussian_actor(network: nn.Module, in_keys: list[str], action_spec: TensorSpec | None) -> ProbabilisticActor:
    """``network(in_keys) -> loc, scale``, then the masked Gaussian over the action slots.

    As :func:`unipolicy_rl.networks.make_actor`: the behaviour policy's ``loc``/``scale`` and
    log-probability are stored with every step (TRPO's ratio and KL need them), exploration is on
    by default; here the distribution also reads ``ACTION_MASK`` from the data.
    """
    return ProbabilisticActor(
        TensorDictModule(network, in_keys=in_keys, out_keys=["loc", "scale"]),
        in_keys={"loc": "loc", "scale": "scale", "mask": ACTION_MASK},
        spec=action_spec,
        distribution_class=MaskedIndependentNormal,
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )


def make_token_transformer_actor(token_features: int, settings: TokenTransformerSettings | None = None,
                                 init_log_std: float = 0.0, *, max_tokens: int | None = None, tokens_key: str = TOKENS,
                                 action_spec: TensorSpec | None = None) -> ProbabilisticActor:
    """The token transformer's Gaussian policy, reading ``tokens_key`` (normalised tokens), the
    token mask and parents, and the action mask; ``max_tokens`` sizes the slot embedding (needed
    only with ``settings.slot_embedding``)."""
    network = _TransformerActorNetwork(token_features, settings or TokenTransformerSettings(), init_log_std,
                                       max_tokens)
    return _gaussian_actor(network, [tokens_key, TOKEN_MASK, TOKEN_PARENT], action_spec)


def make_token_transformer_critic(token_features: int, settings: TokenTransformerSettings | None = None, *,
                                  max_tokens: int | None = None, tokens_key: str = TOKENS) -> ValueOperator:
    """State value from the mean of the encoded real tokens (its own encoder: the critic's Adam
    must not move the policy TRPO just bounded)."""
    network = _TransformerCriticNetwork(token_features, settings or TokenTransformerSettings(), max_tokens)
    return ValueOperator(network, in_keys=[tokens_key, TOKEN_MASK, TOKEN_PARENT])


def make_padded_mlp_actor(token_features: int, max_tokens: int, hidden_sizes: Sequence[int] = (64, 64),
                          activation: str = "tanh", init_log_std: float = 0.0, *, tokens_key: str = TOKENS,
                          action_spec: TensorSpec | None = None) -> ProbabilisticActor:
    """The padded-MLP baseline's Gaussian policy, the same interface as the transformer's."""
    network = _PaddedMLPActorNetwork(token_features, max_tokens, tuple(hidden_sizes), activation, init_log_std)
    return _gaussian_actor(network, [tokens_key, TOKEN_MASK], action_spec)


def make_modular_actor(token_features: int, hidden_sizes: Sequence[int] = (64, 64), activation: str = "tanh",
                       init_log_std: float = 0.0, *, tokens_key: str = TOKENS, clock: bool = False,
                       action_spec: TensorSpec | None = None) -> ProbabilisticActor:
    """The modular policy's Gaussian policy (:class:`_ModularActorNetwork`): one controller shared
    by every joint of any robot, the same interface as the transformer's; with ``clock`` it also
    reads the env's ``CLOCK`` (an env built with a clock frequency)."""
    network = _ModularActorNetwork(token_features, tuple(hidden_sizes), activation, init_log_std, clock)
    return _gaussian_actor(network, [tokens_key, TOKEN_MASK, TOKEN_PARENT, *([CLOCK] if clock else [])], action_spec)


def make_padded_mlp_critic(token_features: int, max_tokens: int, hidden_sizes: Sequence[int] = (64, 64),
                           activation: str = "tanh", *, tokens_key: str = TOKENS) -> ValueOperator:
    """The padded-MLP baseline's state value."""
    network = PaddedTokenMLP(token_features, max_tokens, 1, tuple(hidden_sizes), activation, output_gain=1.0)
    return ValueOperator(network, in_keys=[tokens_key, TOKEN_MASK])


def make_pooled_token_critic(token_features: int, hidden_sizes: Sequence[int] = (64, 64), activation: str = "tanh",
                             *, tokens_key: str = TOKENS) -> ValueOperator:
    """The pooled token MLP's state value (:class:`PooledTokenCritic`): the cheap critic beside a
    token policy, for any robot and any padding."""
    return ValueOperator(PooledTokenCritic(token_features, hidden_sizes, activation), in_keys=[tokens_key, TOKEN_MASK])
