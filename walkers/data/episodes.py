"""Recorded episodes (offline datasets). On-policy agents collect theirs in
:class:`walkers.data.rollouts.Rollout`."""

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
