"""A test double of an off-policy learner, to show the training loop admits one.

It keeps its own replay buffer (TorchRL's), adds every batch the loop hands it, and takes
``updates_per_step`` gradient steps per new transition on minibatches drawn from the whole
buffer, the shape of SAC's update (here on a plain behaviour-cloning loss: what it learns is
not the point, where its data and steps come from is). Its policy is the TRPO actor, so the
run's checkpoint loads with ``load_policy`` as any other.
"""

from __future__ import annotations

import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer

from unipolicy_rl.observation_statistics import ObservationStatistics
from unipolicy_rl.policy import make_actor_critic, make_collecting_policy, make_observation_norm


class ReplayLearner:
    def __init__(self, cfg, observation_dim: int, action_dim: int, updates_per_step: int = 2,
                 batch_size: int = 8) -> None:
        self.actor, _ = make_actor_critic(cfg, observation_dim, action_dim)
        self.normalizer = make_observation_norm(observation_dim)
        self.policy = make_collecting_policy(self.normalizer, self.actor)
        self.statistics = ObservationStatistics(observation_dim)
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(100_000), batch_size=batch_size)
        self.optimizer = torch.optim.Adam(self.actor.parameters(), lr=1e-3)
        self.updates_per_step = updates_per_step
        self.gradient_steps = 0
        self.batch_keys = ("observation", "action")

    def update(self, batch) -> dict[str, float]:
        new = batch.reshape(-1).select(*self.batch_keys)
        self.buffer.extend(new)
        for _ in range(self.updates_per_step * new.numel()):
            sample = self.normalizer(self.buffer.sample())
            loc = self.actor.get_dist_params(sample)["loc"]
            loss = (loc - sample["action"]).pow(2).mean()
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            self.gradient_steps += 1
        return {"train/gradient_steps": float(self.gradient_steps), "train/buffer_size": float(len(self.buffer))}

    def refresh_observation_normalizer(self, batch) -> dict[str, float]:
        self.statistics.update(batch["observation"])
        self.statistics.copy_to(self.normalizer)
        return {}

    def policy_state(self) -> dict:
        return {"actor": self.actor.state_dict(), "observation_loc": self.statistics.loc,
                "observation_scale": self.statistics.scale}

    def start_from_policy(self, policy: dict) -> None:
        self.actor.load_state_dict(policy["actor"])

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "optimizer": self.optimizer.state_dict(),
                "statistics": self.statistics.state_dict(), "buffer": self.buffer.state_dict(),
                "gradient_steps": self.gradient_steps}

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.statistics.load_state_dict(state["statistics"])
        self.statistics.copy_to(self.normalizer)
        self.buffer.load_state_dict(state["buffer"])
        self.gradient_steps = state["gradient_steps"]

    def close(self) -> None:
        """Nothing runs beside it."""
