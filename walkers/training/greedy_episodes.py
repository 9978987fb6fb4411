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


def run_population_episodes(
    population, envs: Sequence[gym.Env], start_seeds: Sequence[Sequence[int]]
) -> np.ndarray:
    """``(K, episodes)`` returns of a population's K members' greedy episodes, member k's
    episode j from ``envs[k].reset(seed=start_seeds[k][j])``, as :func:`run_episodes` plays
    them one member at a time; here the K members' j-th episodes play together, one batched
    greedy forward of all members a step (``act_population``: the forward their training acts
    through), a member whose episode is over waiting for the others."""
    k, episodes = len(envs), len(start_seeds[0])
    returns = np.zeros((k, episodes))
    for j in range(episodes):
        starts = zip(envs, start_seeds, strict=True)
        obs = np.stack([env.reset(seed=int(seeds[j]))[0] for env, seeds in starts])
        playing = list(range(k))
        while playing:
            actions = population.act_population(obs, explore=False)
            still = []
            for i in playing:
                obs[i], reward, terminated, truncated, _ = envs[i].step(actions[i])
                returns[i, j] += reward
                if not (terminated or truncated):
                    still.append(i)
            playing = still
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
