"""Fixed-length windows of episodes for sequence models (the Decision Transformer)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from walkers.data.episodes import Episode
from walkers.seeding import restore_generator


class SequenceBatch(NamedTuple):
    returns_to_go: torch.Tensor  # (B, K) scaled by the return scale
    obs: torch.Tensor  # (B, K, obs_dim) normalized
    actions: torch.Tensor  # (B, K, act_dim) in [-1, 1]
    timesteps: torch.Tensor  # (B, K) long
    mask: torch.Tensor  # (B, K) 1.0 for real steps, 0.0 for padding after the episode's end


class SequenceSampler:
    """Windows of ``context`` consecutive steps of whole episodes, for sequence models (DT).

    A window starts at a step drawn uniformly from the whole dataset (so an episode is drawn in
    proportion to its length, as in the reference code) and is cut at its episode's end; the rest
    is zero padding, marked in ``mask``. Everything is precomputed once into flat tensors on
    ``device``: observations normalized, actions mapped to [-1, 1], undiscounted returns-to-go
    divided by ``return_scale``, timesteps clipped to ``max_timestep - 1``.
    """

    def __init__(
        self,
        episodes: list[Episode],
        context: int,
        *,
        obs_mean: np.ndarray,
        obs_std: np.ndarray,
        action_center: np.ndarray,
        action_half_range: np.ndarray,
        return_scale: float,
        max_timestep: int,
        device="cpu",
        seed: int = 0,
    ):
        self.context = context
        self.device = torch.device(device)
        obs = np.concatenate([e.observations[:-1] for e in episodes])
        actions = np.concatenate([e.actions for e in episodes])
        rtg = np.concatenate([np.cumsum(e.rewards[::-1])[::-1] for e in episodes])
        timesteps = np.concatenate([np.arange(len(e.rewards)) for e in episodes])
        lengths = np.array([len(e.rewards) for e in episodes])
        # for every step: one past the last step of its episode
        ends = np.repeat(np.cumsum(lengths), lengths)

        def tensor(x, dtype=torch.float32):
            return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype, device=self.device)

        self.obs = tensor((obs - obs_mean) / obs_std)
        self.actions = tensor(np.clip((actions - action_center) / action_half_range, -1, 1))
        self.returns_to_go = tensor(rtg / return_scale)
        self.timesteps = tensor(np.minimum(timesteps, max_timestep - 1), torch.long)
        self.ends = tensor(ends, torch.long)
        self.offsets = torch.arange(context, device=self.device)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)

    def __len__(self) -> int:
        return len(self.obs)

    def sample(self, batch_size: int) -> SequenceBatch:
        start = torch.randint(
            0, len(self), (batch_size,), device=self.device, generator=self.generator
        )
        idx = start[:, None] + self.offsets  # (B, K)
        valid = idx < self.ends[start][:, None]
        idx = torch.where(valid, idx, start[:, None])  # padding reads a real step, then zeroed
        mask = valid.to(torch.float32)
        return SequenceBatch(
            self.returns_to_go[idx] * mask,
            self.obs[idx] * mask[..., None],
            self.actions[idx] * mask[..., None],
            self.timesteps[idx] * valid,
            mask,
        )

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        restore_generator(self.generator, state["generator"], "the sequence sampler")
