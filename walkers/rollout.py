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
    render_episodes: int | None = None,
) -> np.ndarray:
    """Returns of ``episodes`` greedy episodes; episode ``i`` starts from ``reset(seed=seed + i)``.

    Seeding every episode makes evaluations comparable across checkpoints and runs (the same
    start states each time). ``on_frame(episode, frame)`` receives the rendered frames of the
    first ``render_episodes`` episodes (all when None); the env needs ``render_mode="rgb_array"``.
    """
    returns = np.zeros(episodes)
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        agent.begin_episode()
        render = on_frame is not None and (render_episodes is None or i < render_episodes)
        done = False
        while not done:
            if render:
                on_frame(i, env.render())
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, explore=False))
            agent.record_reward(float(reward))
            returns[i] += reward
            done = terminated or truncated
    return returns


def record_episodes(
    agent: Agent, env: gym.Env, episodes: int, seed: int, render_episodes: int = 1
) -> tuple[np.ndarray, list[np.ndarray], float]:
    """:func:`run_episodes` keeping the first ``render_episodes``: (returns, frames, fps)."""
    frames: list[np.ndarray] = []
    returns = run_episodes(
        agent, env, episodes, seed, lambda _, frame: frames.append(frame), render_episodes
    )
    return returns, frames, env.metadata.get("render_fps") or 30
