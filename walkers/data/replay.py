"""The replay buffer of the off-policy agents, and its transitions cut back into episodes."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from walkers.data.episodes import Episode
from walkers.seeding import RandomStreams

log = logging.getLogger("walkers")


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
    """The ring buffers of a population's K members (one for a single agent), as one set of
    preallocated ``(K, capacity, ...)`` float32 tensors on ``device``.

    Stores what the off-policy agents read (obs, action, reward, next_obs, terminated): about
    170 MB per member for 1M Walker2d transitions, plus one byte per transition marking episode
    ends, so a saved buffer can be cut back into episodes (a "replay" dataset,
    :mod:`walkers.collect`). The members step together, so they hold equally many transitions.
    :meth:`sample` draws every member's mini-batch in one op, member k's rows from its own
    counter-based stream (:class:`~walkers.seeding.RandomStreams`, keyed by its seed), so
    a seeded run samples the same batches every time, on any device, and a member samples what a
    single run of its seed samples. A member's :meth:`member_state_dict` is a single agent's
    :meth:`state_dict`.
    """

    def __init__(
        self, capacity: int, obs_dim: int, act_dim: int, device="cpu", seeds: Sequence[int] = (0,)
    ):
        self.capacity, self.members = int(capacity), len(seeds)
        self.device = torch.device(device)
        kw = dict(dtype=torch.float32, device=self.device)
        k, n = self.members, self.capacity
        self.obs = torch.empty(k, n, obs_dim, **kw)
        self.next_obs = torch.empty(k, n, obs_dim, **kw)
        self.action = torch.empty(k, n, act_dim, **kw)
        self.reward = torch.empty(k, n, **kw)
        self.terminated = torch.empty(k, n, **kw)
        self.episode_end = torch.zeros(k, n, dtype=torch.bool, device=self.device)
        self.pos = 0
        self.size = 0
        self._size_t = torch.zeros((), dtype=torch.int64, device=self.device)  # size, for sample
        self.holds_dataset = False  # a fixed dataset's transitions (hold_dataset), never refilled
        self.sampler = RandomStreams.of_seeds(seeds, "replay", self.device)
        self._rows = torch.arange(k, device=self.device)[:, None]
        # what add() writes a step into, in DATA_FIELDS' order: numpy views of the columns on the
        # CPU (they share the tensors' memory, which loading and hold_dataset write in place)
        columns = [getattr(self, name) for name in DATA_FIELDS]
        on_cpu = self.device.type == "cpu"
        self._host_columns = [column.numpy() if on_cpu else column for column in columns]

    def __len__(self) -> int:
        return self.size

    def add(self, obs, action, reward, next_obs, terminated, episode_end=False) -> None:
        """One transition per member: ``(K, ...)`` arrays or lists (or one member's, for K = 1).
        A step of the training loop: on the CPU it writes through numpy views of the columns
        (a few microseconds), elsewhere it copies each field to the device."""
        i = self.pos
        values = (obs, action, reward, next_obs, terminated, episode_end)
        for column, value in zip(self._host_columns, values, strict=True):
            if isinstance(column, np.ndarray):
                column[:, i] = value
            else:
                column[:, i] = torch.as_tensor(np.asarray(value), dtype=column.dtype)
        self.pos = (i + 1) % self.capacity
        if self.size < self.capacity:
            self._set_size(self.size + 1)

    def _set_size(self, size: int) -> None:
        """The size, and its copy on the device that :meth:`sample` reads (no host value is
        baked into a captured update: the same graph samples from a growing buffer)."""
        self.size = size
        self._size_t.fill_(size)

    def hold_dataset(self, data: dict[str, torch.Tensor]) -> None:
        """Fill the buffer with a fixed dataset's transitions (``data``: a tensor per field of
        :data:`DATA_FIELDS`, ``episode_end`` optional), for good: an offline agent's. A
        checkpoint's sampler state loaded later leaves them in place."""
        n = len(data["obs"])
        for name, values in data.items():
            getattr(self, name)[:, :n] = values.to(self.device)
        self.pos, self.holds_dataset = 0, True
        self._set_size(n)

    def sample(self, batch_size: int) -> Batch:
        """Every member's mini-batch, ``(K, batch_size, ...)`` tensors, and the rows drawn."""
        idx = self.draw_rows(batch_size)
        rows = self._rows
        return Batch(
            self.obs[rows, idx],
            self.action[rows, idx],
            self.reward[rows, idx],
            self.next_obs[rows, idx],
            self.terminated[rows, idx],
            idx,
        )

    def draw_rows(self, batch_size: int) -> torch.Tensor:
        """``(K, batch_size)`` rows, uniform over each member's transitions, from its stream."""
        return self.sampler.integers(self._size_t, batch_size)

    def state_dict(self, with_data: bool) -> dict:
        """A single agent's buffer state (member 0 of a population of one)."""
        return self.member_state_dict(0, with_data)

    def member_state_dict(self, i: int, with_data: bool) -> dict:
        """Member ``i``'s as a single agent's: the sampler state always; the transitions
        themselves only ``with_data`` (they are large)."""
        state = {"pos": self.pos, "size": self.size, "sampler": self.sampler.member_state_dict(i)}
        if with_data:
            n = self.size
            state["data"] = {name: getattr(self, name)[i, :n].cpu().clone() for name in DATA_FIELDS}
        return state

    def load_state_dict(self, state: dict) -> None:
        self.load_member_state_dict(0, state)

    def load_member_state_dict(self, i: int, state: dict) -> None:
        """A single agent's buffer state into member ``i`` (the position, size and sampler are
        the members' in common: the last member loaded sets them)."""
        if "sampler" in state:
            self.sampler.load_member_state_dict(i, state["sampler"])
        else:  # saved by a walkers that sampled with a torch.Generator: a stream of its own
            log.warning(
                "the replay buffer's sampler was saved by an older walkers (a torch.Generator); "
                "it goes on with its new stream from the start: other batches than that run's"
            )
        if "data" in state:
            for name, values in state["data"].items():
                getattr(self, name)[i, : len(values)] = values.to(self.device)
            self.pos = state["pos"]
            self._set_size(state["size"])
        elif not self.holds_dataset:  # restarted without its transitions: refill from empty
            self.pos = 0
            self._set_size(0)


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
