"""Environments from an env config: gymnasium id, time limit, kwargs, optional reward shaping.

Every training env records the *true* episode return before any shaping wrapper
(``RecordEpisodeStatistics`` is the innermost wrapper), so what the platform reports is always the
environment's own return. Evaluation envs get no shaping at all.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import gymnasium as gym
import numpy as np

from walkers.agents.base import Transition
from walkers.errors import ConfigError

#: PyOpenGL (MuJoCo's renderer) says at INFO that an optional accelerator is not installed.
logging.getLogger("OpenGL").setLevel(logging.WARNING)


class FallPenaltyWrapper(gym.Wrapper):
    """The BipedalWalker tutorial's fall handling: a reward of -100 (falling) becomes ``-1``.

    The episode still terminates there. Only the learning signal changes, never the reported return.
    """

    def __init__(self, env: gym.Env, fall_reward: float = -1.0):
        super().__init__(env)
        self.fall_reward = fall_reward

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if reward <= -100:
            reward = self.fall_reward
        return obs, reward, terminated, truncated, info


def make_env(env_cfg, *, shaping: bool = True, render_mode: str | None = None) -> gym.Env:
    """Build one environment from an env config (``id``, ``max_episode_steps``, ``kwargs``...).

    Raises :class:`ConfigError` for an unknown id or a non-continuous action space.
    """
    env_id = env_cfg["id"]
    if env_id not in gym.registry:
        raise ConfigError(
            f"env.id={env_id!r} is not a registered Gymnasium environment "
            "(e.g. Walker2d-v5, Hopper-v5, Pendulum-v1; see gymnasium.pprint_registry())"
        )
    kwargs = dict(env_cfg.get("kwargs") or {})
    env = gym.make(
        env_id,
        max_episode_steps=env_cfg.get("max_episode_steps"),
        render_mode=render_mode,
        **kwargs,
    )
    if not isinstance(env.action_space, gym.spaces.Box):
        env.close()
        raise ConfigError(
            f"env.id={env_id!r} has a {type(env.action_space).__name__} action space; "
            "walkers' algorithms need a continuous (Box) action space"
        )
    env = gym.wrappers.RecordEpisodeStatistics(env)
    if shaping and env_cfg.get("fall_penalty") is not None:
        env = FallPenaltyWrapper(env, env_cfg["fall_penalty"])
    return env


def make_vector_env(env_cfg, num_envs: int) -> gym.vector.SyncVectorEnv:
    """``num_envs`` training envs (:func:`make_env`) stepped together in this process, a finished
    episode reset in the same step (its last observation in ``info["final_obs"]``, its
    statistics in ``info["final_info"]``). Reset with ``seed=s``, env ``i`` starts from seed
    ``s + i`` (Gymnasium's rule), so env 0 starts as a single-env run of the same seed does.

    In-process by measurement (``make bench-envs``): on 2 cores, AsyncVectorEnv's worker
    processes stepped Walker2d-v5 at 0.38x one env alone, their messages costing more than the
    step; the gain of several envs is acting on them as one batch."""
    same_step = gym.vector.AutoresetMode.SAME_STEP
    return gym.vector.SyncVectorEnv(
        [lambda: make_env(env_cfg)] * num_envs, autoreset_mode=same_step
    )


class VectorStep(NamedTuple):
    """One step of every env of a vector env (:func:`step_vector_env`)."""

    next_obs: np.ndarray  # what each env shows now: a finished episode's env already reset
    transitions: list[Transition]  # each env's step, its own last observation where it ended
    info: dict
    ended: np.ndarray  # the envs whose episode ended in the step


def step_vector_env(envs: gym.vector.VectorEnv, obs: np.ndarray, actions) -> VectorStep:
    """Step every env of ``envs`` (finishing episodes in the step, :func:`make_vector_env`)
    from observations ``obs`` with ``actions``."""
    next_obs, rewards, terminated, truncated, info = envs.step(actions)
    ended = np.flatnonzero(terminated | truncated)
    own_next_obs = next_obs.copy()  # a finished episode's own last observation, not the next
    for i in ended:  # episode's first
        own_next_obs[i] = info["final_obs"][i]
    transitions = [
        Transition(
            obs[i],
            actions[i],
            float(rewards[i]),
            own_next_obs[i],
            bool(terminated[i]),
            bool(truncated[i]),
        )  # fmt: skip
        for i in range(envs.num_envs)
    ]
    return VectorStep(next_obs, transitions, info, ended)


def env_spaces(env: gym.Env) -> dict:
    """The shapes an agent is built from."""
    return {
        "obs_dim": int(np.prod(env.observation_space.shape)),
        "action_low": env.action_space.low.tolist(),
        "action_high": env.action_space.high.tolist(),
    }
