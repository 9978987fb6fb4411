"""Deterministic policy rollouts (evaluation), shared by the trainer and ``walkers.evaluate``."""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
import numpy as np

from walkers.agents.base import Agent


def run_episodes(
    agent: Agent,
    env: gym.Env,
    episodes: int,
    seed: int,
    on_frame: Callable[[int, np.ndarray], None] | None = None,
) -> np.ndarray:
    """Returns of ``episodes`` greedy episodes; episode ``i`` starts from ``reset(seed=seed + i)``.

    Seeding every episode makes evaluations comparable across checkpoints and runs (the same
    start states each time). ``on_frame(episode, frame)`` receives rendered frames when the env
    has a render mode.
    """
    returns = np.zeros(episodes)
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        done = False
        while not done:
            if on_frame is not None:
                on_frame(i, env.render())
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, explore=False))
            returns[i] += reward
            done = terminated or truncated
    return returns
