"""Observation normalization and reward scaling *inside* an agent (PPO's reference practice).

The reference implementations normalize in env wrappers (Gymnasium's ``NormalizeObservation`` /
``NormalizeReward``, Stable-Baselines3's ``VecNormalize``). Here the env stays the env's own, so
``train/episode_return`` and every evaluation are the env's true returns, and the statistics live
in the agent: they update only while it explores (training), are used frozen by greedy actions
(evaluation, ``walkers.evaluate``, ``walkers.collect``), and are part of its checkpoint.
"""

from __future__ import annotations

import numpy as np


class RunningMeanStd:
    """Running mean and variance of a stream of arrays (the parallel update of Chan et al.,
    as in the reference wrappers), starting from mean 0, variance 1, a pseudo-count ``epsilon``."""

    def __init__(self, shape: tuple[int, ...] = (), epsilon: float = 1e-4):
        self.mean = np.zeros(shape, np.float64)
        self.var = np.ones(shape, np.float64)
        self.count = epsilon

    def update(self, x: np.ndarray) -> None:
        """Add a batch ``(n, *shape)`` of samples."""
        batch_mean, batch_var, n = x.mean(axis=0), x.var(axis=0), x.shape[0]
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.var, self.count = m2 / total, total

    def state_dict(self) -> dict:
        return {"mean": self.mean.copy(), "var": self.var.copy(), "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean = np.array(state["mean"], np.float64)
        self.var = np.array(state["var"], np.float64)
        self.count = float(state["count"])


class ObservationNormalizer:
    """(obs - mean) / sqrt(var + eps), clipped to [-clip, clip]; the identity when disabled."""

    def __init__(self, shape: tuple[int, ...], enabled: bool, clip: float = 10.0, eps=1e-8):
        self.enabled, self.clip, self.eps = enabled, clip, eps
        self.rms = RunningMeanStd(shape)

    def __call__(self, obs: np.ndarray, update: bool) -> np.ndarray:
        """``obs`` normalized (float32), one observation or a batch ``(N, *shape)``;
        ``update``: add it to the statistics first."""
        obs = np.asarray(obs, np.float32)
        if not self.enabled:
            return obs
        if update:
            self.rms.update(obs if obs.ndim > self.rms.mean.ndim else obs[None])
        normalized = (obs - self.rms.mean) / np.sqrt(self.rms.var + self.eps)
        return np.clip(normalized, -self.clip, self.clip).astype(np.float32)

    def state_dict(self) -> dict:
        return self.rms.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.rms.load_state_dict(state)


class RewardScaler:
    """r / sqrt(Var[R] + eps), clipped to [-clip, clip], with R the running discounted return of
    the current episode, R <- gamma * R + r, reset at every episode end (Stable-Baselines3's
    ``VecNormalize``; the mean is not subtracted: it would change the problem). The identity when
    disabled. With ``num_envs`` > 1 each env has its own R and the statistics are shared
    (:meth:`scale_batch`, as ``VecNormalize`` over a vector env)."""

    def __init__(
        self, gamma: float, enabled: bool, clip: float = 10.0, eps: float = 1e-8, *, num_envs=1
    ):
        self.gamma, self.enabled, self.clip, self.eps = gamma, enabled, clip, eps
        self.rms = RunningMeanStd()
        self.num_envs = num_envs
        self.discounted_return = 0.0 if num_envs == 1 else np.zeros(num_envs)

    def __call__(self, reward: float, episode_end: bool) -> float:
        """The scaled reward of a training step (the statistics update with it)."""
        if not self.enabled:
            return reward
        self.discounted_return = self.discounted_return * self.gamma + reward
        self.rms.update(np.asarray([self.discounted_return]))
        scaled = reward / float(np.sqrt(self.rms.var + self.eps))
        if episode_end:
            self.discounted_return = 0.0
        return float(np.clip(scaled, -self.clip, self.clip))

    def scale_batch(self, rewards: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
        """The scaled rewards of one step of the ``num_envs`` envs ``(N,)``: every env's R moves,
        then the statistics take the N returns at once."""
        rewards = np.asarray(rewards, np.float64)
        if not self.enabled:
            return rewards
        self.discounted_return = self.discounted_return * self.gamma + rewards
        self.rms.update(self.discounted_return)
        scaled = rewards / np.sqrt(self.rms.var + self.eps)
        self.discounted_return[np.asarray(episode_ends, bool)] = 0.0
        return np.clip(scaled, -self.clip, self.clip)

    def new_episode(self) -> None:
        """The current episodes are over without an episode end seen (a resumed run)."""
        self.discounted_return = 0.0 if self.num_envs == 1 else np.zeros(self.num_envs)

    def state_dict(self) -> dict:
        returns = self.discounted_return
        return {
            "rms": self.rms.state_dict(),
            "discounted_return": returns if self.num_envs == 1 else returns.tolist(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.rms.load_state_dict(state["rms"])
        returns = state["discounted_return"]
        if self.num_envs == 1:
            self.discounted_return = float(returns)
        else:
            self.discounted_return = np.asarray(returns, np.float64).reshape(self.num_envs)
