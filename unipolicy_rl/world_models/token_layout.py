"""The state of a world model of grammar robots: every link's token, padded, as one flat vector.

A :class:`~unipolicy_rl.envs.MorphologyWalkerEnv` observes a robot as link tokens ``[L, F]``
(:mod:`unipolicy_rl.envs.tokens`): the moving features (position, velocity, orientation, angular
velocity, joint angle and rate) are the robot's whole state, and the built ones (hinge axis,
kind, size) say what the link is. So the tokens are the world model's state, with nothing to
add or drop; what everything downstream of a :class:`~unipolicy_rl.world_models.Dynamics`
needs of it is here, as :class:`~unipolicy_rl.world_models.StateLayout` gives it for the
vertebrate:

* the state is the tokens flattened, ``[L * F]``: the replay buffer, the trainer's split, the
  members' disagreement and the fresh error all work on rows of numbers, whatever they hold.
  Padding columns and built features never change, so the measures that skip outputs without
  change (:mod:`~unipolicy_rl.world_models.disagreement`, :mod:`~unipolicy_rl.world_models.fresh_error`)
  skip them.
* the root token leads, and its first features are the thesis observation's ``x, y, z, vx``
  (asserted in :mod:`unipolicy_rl.envs.tokens`), so the imagined env's reward head, the real
  env's ``walking_reward`` of the state's first numbers, is the real env's reward of the root
  token, and its fault check the real env's check of all tokens.
* the policy's view is the tokens themselves, with the build keys (masks, parents, which
  morphology) that no step changes: an imagined branch carries them from its real start state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from unipolicy_rl.envs.tokens import ACTION_MASK, MORPHOLOGY, TOKEN_MASK, TOKEN_PARENT, TOKEN_SIZE, TOKENS
from unipolicy_rl.world_models.layout import Layout

# ``world_model.model_state`` of a model of link tokens (the vertebrate's are ``full`` and ``thesis``).
TOKEN_STATE = "tokens"


@dataclass(frozen=True)
class TokenLayout(Layout):
    """``max_links`` link tokens of :data:`~unipolicy_rl.envs.tokens.TOKEN_SIZE` features, flattened."""

    state_key: ClassVar[str] = TOKENS
    observation_key: ClassVar[str] = TOKENS
    build_keys: ClassVar[tuple[str, ...]] = (TOKEN_MASK, TOKEN_PARENT, ACTION_MASK, MORPHOLOGY)
    memory_size: ClassVar[int] = 0
    design_size: ClassVar[int] = 2  # every model takes the robot's (l, rho)

    max_links: int

    def __post_init__(self) -> None:
        if isinstance(self.max_links, bool) or not (isinstance(self.max_links, int) and self.max_links >= 1):
            raise ValueError(f"max_links must be a positive integer (the env's token slots), got {self.max_links!r}")

    @property
    def robot_size(self) -> int:
        return self.max_links * TOKEN_SIZE

    @property
    def size(self) -> int:
        return self.robot_size

    @property
    def observation_shape(self) -> tuple[int, ...]:
        return (self.max_links, TOKEN_SIZE)

    def from_full(self, tokens: torch.Tensor) -> torch.Tensor:
        """The model's state ``[*, L * F]`` of the env's ``tokens`` ``[*, L, F]`` (what the replay buffer stores)."""
        if tuple(tokens.shape[-2:]) != self.observation_shape:
            raise ValueError(f"tokens must end in {self.observation_shape} (max_links, features), "
                             f"got shape {tuple(tokens.shape)}")
        return tokens.flatten(-2)

    def tokens(self, state: torch.Tensor) -> torch.Tensor:
        """``[*, L, F]``: the tokens of a state ``[*, L * F]``."""
        return state.unflatten(-1, self.observation_shape)

    def observation(self, state: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """What the policy reads of ``state``: its tokens (the design is not told, as in the real env);
        a copy, so the policy's tokens and the model's state never alias within a step."""
        return self.tokens(state).clone()
