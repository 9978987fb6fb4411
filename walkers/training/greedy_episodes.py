"""Deterministic policy rollouts (evaluation), shared by the trainer and ``walkers.evaluate``."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import gymnasium as gym
import numpy as np

from walkers.agents.base import Agent


def run_episodes(
    agent: Agent,
    env: gym.Env,
    start_seeds: Sequence[int],
    on_frame: Callable[[int, np.ndarray], None] | None = None,
    render_episodes: int | None = None,
) -> np.ndarray:
    """Returns of one greedy episode per start seed; episode ``i`` starts from
    ``reset(seed=start_seeds[i])`` (a run's are :func:`walkers.seeding.eval_start_seeds`).

    Seeding every episode makes a run's evaluations comparable across its checkpoints (the same
    start states each time). ``on_frame(episode, frame)`` receives the rendered frames of the
    first ``render_episodes`` episodes (all when None); the env needs ``render_mode="rgb_array"``.
    """
    returns = np.zeros(len(start_seeds))
    for i, start_seed in enumerate(start_seeds):
        obs, _ = env.reset(seed=int(start_seed))
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
    agent: Agent, env: gym.Env, start_seeds: Sequence[int], render_episodes: int = 1
) -> tuple[np.ndarray, list[np.ndarray], float]:
    """:func:`run_episodes` keeping the first ``render_episodes``: (returns, frames, fps)."""
    frames: list[np.ndarray] = []
    returns = run_episodes(
        agent, env, start_seeds, lambda _, frame: frames.append(frame), render_episodes
    )
    return returns, frames, env.metadata.get("render_fps") or 30
