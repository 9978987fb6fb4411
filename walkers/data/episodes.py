"""Whole episodes: recorded (offline datasets) and collected for Monte-Carlo updates (REINFORCE)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Episode(NamedTuple):
    """One recorded episode: ``observations`` has one row more than the steps (the last one)."""

    observations: np.ndarray  # (T + 1, obs_dim) float32
    actions: np.ndarray  # (T, act_dim) float32
    rewards: np.ndarray  # (T,)
    terminations: np.ndarray  # (T,) bool
    truncations: np.ndarray  # (T,) bool

    @property
    def episode_return(self) -> float:
        return float(np.sum(self.rewards))


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
