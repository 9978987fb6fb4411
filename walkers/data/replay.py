"""The replay buffer of the off-policy agents, and its transitions cut back into episodes."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from walkers.data.episodes import Episode
from walkers.seeding import restore_generator


class Batch(NamedTuple):
    """A mini-batch of transitions, and where in the buffer each came from."""

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor  # 1.0 where the episode really ended (no bootstrap), else 0.0
    #: the buffer rows sampled (e.g. to update their priorities), None for a made-up batch
    index: torch.Tensor | None = None


DATA_FIELDS = ("obs", "action", "reward", "next_obs", "terminated", "episode_end")


class ReplayBuffer:
    """Ring buffer of transitions in preallocated float32 tensors on ``device``.

    Stores what TD3/DDPG read (obs, action, reward, next_obs, terminated): about 170 MB for 1M
    Walker2d transitions, plus one byte per transition marking episode ends, so a saved buffer
    can be cut back into episodes (a "replay" dataset, :mod:`walkers.collect`). Sampling draws
    indices with its own ``torch.Generator`` so a seeded run samples the same batches every time.
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
        self.episode_end = torch.zeros(self.capacity, dtype=torch.bool, device=self.device)
        self.pos = 0
        self.size = 0
        self.holds_dataset = False  # a fixed dataset's transitions (hold_dataset), never refilled
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)

    def __len__(self) -> int:
        return self.size

    def add(
        self, obs, action, reward: float, next_obs, terminated: bool, episode_end: bool = False
    ) -> None:
        i = self.pos
        self.obs[i] = torch.as_tensor(obs)
        self.action[i] = torch.as_tensor(action)
        self.reward[i] = reward
        self.next_obs[i] = torch.as_tensor(next_obs)
        self.terminated[i] = float(terminated)
        self.episode_end[i] = episode_end
        self.pos = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def hold_dataset(self, data: dict[str, torch.Tensor]) -> None:
        """Fill the buffer with a fixed dataset's transitions (``data``: a tensor per field of
        :data:`DATA_FIELDS`, ``episode_end`` optional), for good: an offline agent's. A
        checkpoint's sampler state loaded later leaves them in place."""
        n = len(data["obs"])
        for name, values in data.items():
            getattr(self, name)[:n] = values.to(self.device)
        self.pos, self.size, self.holds_dataset = 0, n, True

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
            idx,
        )

    def state_dict(self, with_data: bool) -> dict:
        """Sampler state always; the transitions themselves only ``with_data`` (they are large)."""
        state = {"pos": self.pos, "size": self.size, "generator": self.generator.get_state()}
        if with_data:
            n = self.size
            state["data"] = {name: getattr(self, name)[:n].cpu().clone() for name in DATA_FIELDS}
        return state

    def load_state_dict(self, state: dict) -> None:
        restore_generator(self.generator, state["generator"], "the replay buffer's sampler")
        if "data" in state:
            for name, values in state["data"].items():
                getattr(self, name)[: len(values)] = values.to(self.device)
            self.pos, self.size = state["pos"], state["size"]
        elif not self.holds_dataset:  # restarted without its transitions: refill from empty
            self.pos, self.size = 0, 0


def first_steps(state: dict, n: int, steps_seen: int) -> dict:
    """A saved buffer (``state_dict(with_data=True)``) cut back to the transitions of the run's
    first ``n`` env steps, ``steps_seen`` being how many it took in all: what the run had seen when
    it was ``n`` steps in (a "medium-replay" dataset of a run that went on). The buffer must still
    hold them: a ring that has wrapped has overwritten its oldest transitions."""
    if steps_seen > state["size"]:
        raise ValueError(
            f"the buffer holds the last {state['size']:,} of {steps_seen:,} steps: "
            "its first steps were overwritten"
        )
    if not 0 < n <= steps_seen:
        raise ValueError(f"must be between 1 and the {steps_seen:,} steps the run took")
    data = {name: values[:n] for name, values in state["data"].items()}
    return {**state, "pos": n, "size": n, "data": data}


def replay_episodes(state: dict) -> list[Episode]:
    """The whole episodes in a saved replay buffer (``state_dict(with_data=True)``), oldest first.

    The newest episode may be unfinished and, once the ring has wrapped (``size == capacity``), the
    oldest one has lost its start: both are dropped.
    """
    data = {k: v.numpy() for k, v in state["data"].items()}
    if "episode_end" not in data:
        raise ValueError("this replay buffer was saved without episode ends (an older walkers)")
    n, pos = state["size"], state["pos"]
    order = (pos + np.arange(n)) % n if n else np.arange(0)
    data = {k: v[order] for k, v in data.items()}
    ends = np.flatnonzero(data["episode_end"])
    starts = np.r_[0, ends[:-1] + 1]
    wrapped = pos != n
    episodes = []
    for i, (start, end) in enumerate(zip(starts, ends, strict=True)):
        if i == 0 and wrapped:
            continue
        steps = slice(start, end + 1)
        terminated = data["terminated"][steps] > 0.5
        episodes.append(
            Episode(
                observations=np.concatenate([data["obs"][steps], data["next_obs"][end : end + 1]]),
                actions=data["action"][steps],
                rewards=data["reward"][steps],
                terminations=terminated,
                truncations=data["episode_end"][steps] & ~terminated,
            )
        )
    return episodes
