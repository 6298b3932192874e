"""PC-NARX inputs of the one-step PCE: the previous steps' state changes and actions, as memory.

The state a model predicts hides part of the robot (the full layout has no body orientations
or angular rates; the thesis' 18 numbers have no joints). A one-step model that also reads the
previous step's change and action can recover some of it, as a nonlinear autoregressive model
with exogenous input does (PC-NARX: Mai, Spiridonakos, Chatzi and Sudret 2016). ``lags`` such
steps are carried as the model's memory columns after the robot's state
(:attr:`~unipolicy_rl.world_models.StateLayout.memory_size`), most recent first, each a block
of the robot's change over that step then the (clamped) action taken in it:

    memory = [change(t-1), action(t-1), change(t-2), action(t-2), ...]

Real data get them from their episodes (:meth:`LagMemory.of_episodes`; zeros for the steps
before an episode's start), so a branch that starts from a buffered real state starts with
that state's real past; an imagined step shifts its own predicted change and action in
(:meth:`LagMemory.after_step`), so a branch feeds its own predictions back.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

MAX_LAGS = 2  # each lag adds robot_size + action_dim inputs (102 for the full state): the basis grows fast


def check_lags(lags: int) -> None:
    """Refuses a lag count that is not an integer in [0, MAX_LAGS], by name."""
    if isinstance(lags, bool) or not isinstance(lags, int) or not 0 <= lags <= MAX_LAGS:
        raise ValueError(f"world_model.model.lags must be an integer in [0, {MAX_LAGS}] (previous steps whose "
                         f"state change and action are inputs; 0: none), got {lags!r}")


@dataclass(frozen=True)
class LagMemory:
    """``lags`` blocks of ``robot_size`` changes and ``action_dim`` actions (see the module docstring)."""

    lags: int
    robot_size: int
    action_dim: int

    def __post_init__(self) -> None:
        check_lags(self.lags)

    @property
    def block(self) -> int:
        return self.robot_size + self.action_dim

    @property
    def size(self) -> int:
        return self.lags * self.block

    def after_step(self, memory: torch.Tensor, change: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The memory after a step of ``change`` (the robot's) taken with ``action``: that step in
        front, the oldest block dropped. Broadcasts over leading dimensions."""
        shape = torch.broadcast_shapes(memory.shape[:-1], change.shape[:-1], action.shape[:-1])
        newest = torch.cat([change.expand(*shape, -1), action.clamp(-1.0, 1.0).to(change.dtype).expand(*shape, -1)],
                           dim=-1)
        return torch.cat([newest, memory.expand(*shape, -1)[..., :self.size - self.block]], dim=-1)

    def of_episodes(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                    starts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The memory before and after every step of ``[rows, steps]`` real data (``state`` and
        ``next_state`` the robot's, ``starts`` True where a step begins an episode): block k of
        step s is step s - k's, zeros where that step lies before the episode of step s."""
        blocks = torch.cat([next_state - state, action.clamp(-1.0, 1.0).to(state.dtype)], dim=-1)
        episode = starts.long().cumsum(-1)
        steps = blocks.shape[-2]

        def lagged(k: int) -> torch.Tensor:
            """Step s - k's block at step s, where it belongs to step s's episode."""
            if k == 0:
                return blocks
            shifted = torch.cat([blocks.new_zeros(*blocks.shape[:-2], k, self.block), blocks[..., :steps - k, :]], -2)
            earlier = torch.cat([episode.new_full((*episode.shape[:-1], k), -1), episode[..., :steps - k]], -1)
            return torch.where((earlier == episode).unsqueeze(-1), shifted, torch.zeros_like(shifted))

        before = torch.cat([lagged(k) for k in range(1, self.lags + 1)], dim=-1)
        after = torch.cat([lagged(k) for k in range(self.lags)], dim=-1)
        return before, after

    def names(self, state_names: list[str]) -> list[str]:
        """A name per memory column: ``<state name>.change@t-k`` then ``action<j>@t-k``, per lag k."""
        return [name for k in range(1, self.lags + 1)
                for name in [*(f"{s}.change@t-{k}" for s in state_names),
                             *(f"action{j}@t-{k}" for j in range(self.action_dim))]]
