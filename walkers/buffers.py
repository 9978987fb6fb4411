"""Experience storage: a preallocated replay buffer (off-policy), an episode buffer (on-policy)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch


class Batch(NamedTuple):
    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor  # 1.0 where the episode really ended (no bootstrap), else 0.0


class ReplayBuffer:
    """Ring buffer of transitions in preallocated float32 tensors on ``device``.

    Stores exactly what TD3/DDPG read (obs, action, reward, next_obs, terminated): about 170 MB
    for 1M Walker2d transitions. Sampling draws indices with its own ``torch.Generator`` so a
    seeded run samples the same batches every time.
    """

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, device="cpu", seed: int = 0):
        self.capacity = int(capacity)
        self.device = torch.device(device)
        kw = dict(dtype=torch.float32, device=self.device)
        self.obs = torch.empty(self.capacity, obs_dim, **kw)
        self.next_obs = torch.empty(self.capacity, obs_dim, **kw)
        self.action = torch.empty(self.capacity, act_dim, **kw)
        self.reward = torch.empty(self.capacity, **kw)
        self.terminated = torch.empty(self.capacity, **kw)
        self.pos = 0
        self.size = 0
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, obs, action, reward: float, next_obs, terminated: bool) -> None:
        i = self.pos
        self.obs[i] = torch.as_tensor(obs)
        self.action[i] = torch.as_tensor(action)
        self.reward[i] = reward
        self.next_obs[i] = torch.as_tensor(next_obs)
        self.terminated[i] = float(terminated)
        self.pos = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        idx = torch.randint(
            0, self.size, (batch_size,), device=self.device, generator=self.generator
        )
        return Batch(
            self.obs[idx],
            self.action[idx],
            self.reward[idx],
            self.next_obs[idx],
            self.terminated[idx],
        )

    def state_dict(self, with_data: bool) -> dict:
        """Sampler state always; the transitions themselves only ``with_data`` (they are large)."""
        state = {"pos": self.pos, "size": self.size, "generator": self.generator.get_state()}
        if with_data:
            n = self.size
            state["data"] = {
                name: getattr(self, name)[:n].cpu().clone()
                for name in ("obs", "action", "reward", "next_obs", "terminated")
            }
        return state

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        if "data" in state:
            for name, values in state["data"].items():
                getattr(self, name)[: len(values)] = values.to(self.device)
            self.pos, self.size = state["pos"], state["size"]
        else:  # restarted without its transitions: refill from empty
            self.pos, self.size = 0, 0


class EpisodeBuffer:
    """Whole episodes of (obs, action, reward) for Monte-Carlo policy gradients."""

    def __init__(self):
        self.episodes: list[dict[str, np.ndarray]] = []
        self._obs, self._actions, self._rewards = [], [], []

    def add(self, obs, action, reward: float, episode_over: bool) -> None:
        self._obs.append(np.asarray(obs, dtype=np.float32))
        self._actions.append(np.asarray(action, dtype=np.float32))
        self._rewards.append(float(reward))
        if episode_over:
            self.episodes.append(
                {
                    "obs": np.stack(self._obs),
                    "actions": np.stack(self._actions),
                    "rewards": np.asarray(self._rewards, dtype=np.float32),
                }
            )
            self._obs, self._actions, self._rewards = [], [], []

    @property
    def num_episodes(self) -> int:
        return len(self.episodes)

    def pop_episodes(self) -> list[dict[str, np.ndarray]]:
        episodes, self.episodes = self.episodes, []
        return episodes
