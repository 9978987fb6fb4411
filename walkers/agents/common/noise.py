"""Exploration noise of the deterministic actor-critics (DDPG, TD3), one process per member."""

from __future__ import annotations

import numpy as np


class GaussianNoise:
    """i.i.d. N(0, sigma) exploration noise (TD3's)."""

    def __init__(self, sigma: float, size: int, rng: np.random.Generator):
        self.sigma, self.size, self.rng = sigma, size, rng

    def sample(self) -> np.ndarray:
        return self.rng.normal(0.0, self.sigma, self.size)

    def reset(self) -> None:
        pass

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class OrnsteinUhlenbeckNoise(GaussianNoise):
    """Temporally correlated noise x <- x + theta (0 - x) dt + sigma sqrt(dt) N(0, 1) (DDPG paper).

    Reset to zero at the start of every episode.
    """

    def __init__(self, sigma, size, rng, theta: float = 0.15, dt: float = 1e-2):
        super().__init__(sigma, size, rng)
        self.theta, self.dt = theta, dt
        self.x = np.zeros(size)

    def sample(self) -> np.ndarray:
        noise = self.rng.normal(0.0, 1.0, self.size)
        self.x = self.x - self.theta * self.x * self.dt + self.sigma * np.sqrt(self.dt) * noise
        return self.x

    def reset(self) -> None:
        self.x = np.zeros(self.size)

    def state_dict(self) -> dict:
        return {"x": self.x.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.x = state["x"].copy()


NOISE_TYPES = {"gaussian": GaussianNoise, "ou": OrnsteinUhlenbeckNoise}
