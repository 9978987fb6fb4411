"""Environments from an env config: gymnasium id, time limit, kwargs, optional reward shaping.

Every training env records the *true* episode return before any shaping wrapper
(``RecordEpisodeStatistics`` is the innermost wrapper), so what the platform reports is always the
environment's own return. Evaluation envs get no shaping at all.
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
import os
import signal

import gymnasium as gym
import numpy as np
from omegaconf import OmegaConf

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


class EpisodeStatisticsOnly(gym.Wrapper):
    """A step's info cut down to the episode's statistics (``RecordEpisodeStatistics``', at its
    last step), the only entry a training loop reads: a vector env merges every key of every
    env's info into arrays at every step, which for MuJoCo's per-step diagnostics (positions,
    velocities, reward terms) cost about as much as the rest of the loop."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, _episode_only(info)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, _episode_only(info)


def _episode_only(info: dict) -> dict:
    return {"episode": info["episode"]} if "episode" in info else {}


#: ``vector_env=auto`` steps envs in worker processes from this many envs on, given as many cores:
#: on a 16-core machine 16 Walker2d-v5 envs stepped 2.5x faster so, 8 1.5x, 4 no faster; on 2
#: cores the workers' messages cost more than the step (0.38x); docs/speed.md
WORKERS_FROM = 8


def steps_in_workers(vector_env: str, num_envs: int, cores: int | None = None) -> bool:
    """Whether ``vector_env`` (``sync | async | auto``) steps ``num_envs`` envs in worker
    processes on a machine of ``cores`` (this one's by default)."""
    if vector_env != "auto":
        return vector_env == "async"
    return num_envs >= WORKERS_FROM and (cores or os.cpu_count() or 1) >= num_envs


def make_vector_env(
    env_cfg, num_envs: int, step_info: bool = True, vector_env: str = "sync"
) -> gym.vector.VectorEnv:
    """``num_envs`` training envs (:func:`make_env`) stepped together, a finished episode reset
    in the same step (its last observation in ``info["final_obs"]``, its statistics in
    ``info["final_info"]``): in this process, in turn (``vector_env=sync``: Gymnasium's
    ``SyncVectorEnv``), or a worker process each (``async``: ``AsyncVectorEnv``, the same envs,
    the same numbers); ``auto``, the run's default, decides by the machine's cores.
    Reset with ``seed=s``, env ``i`` starts from seed ``s + i`` (Gymnasium's rule), so env 0
    starts as a single-env run of the same seed does; ``seed=[s_0, s_1, ...]`` seeds each env
    with its own (None: unseeded). ``step_info=False`` keeps only the episode statistics of each
    env's info (:class:`EpisodeStatisticsOnly`).

    ``auto`` steps in this process unless the machine has the cores (:func:`steps_in_workers`, by
    measurement: ``make bench-envs``): on 2 cores, AsyncVectorEnv's worker processes stepped
    Walker2d-v5 at 0.38x one env alone, their messages costing more than the step; there the
    gain of several envs is acting on them as one batch."""
    same_step = gym.vector.AutoresetMode.SAME_STEP
    env_cfg = OmegaConf.to_container(env_cfg) if OmegaConf.is_config(env_cfg) else env_cfg
    one_env = functools.partial(_training_env, env_cfg, step_info)
    if steps_in_workers(vector_env, num_envs):
        # forkserver: workers forked from a clean process, never from one holding CUDA or
        # torch's threads (a multirun's second job runs in the first one's process)
        in_worker = functools.partial(_worker_env, one_env)
        return gym.vector.AsyncVectorEnv(
            [in_worker] * num_envs, autoreset_mode=same_step, context="forkserver"
        )
    return gym.vector.SyncVectorEnv([one_env] * num_envs, autoreset_mode=same_step)


def _training_env(env_cfg, step_info: bool) -> gym.Env:
    env = make_env(env_cfg)
    return env if step_info else EpisodeStatisticsOnly(env)


def _worker_env(make) -> gym.Env:
    """An env built in its worker process, which leaves Ctrl-C and SIGTERM to the training
    process: a signal to the whole process group (a terminal's Ctrl-C, ``kill -TERM -<pgid>``)
    must stop the run at its step's end and write its last checkpoint, which reads the workers'
    env RNGs, not kill the workers under it (the training process closes them). Gymnasium
    also calls it once in the training process itself (an env to read the spaces from): there
    the signals stay the run's."""
    if multiprocessing.parent_process() is not None:  # a worker, not the training process
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return make()


def env_spaces(env: gym.Env) -> dict:
    """The shapes an agent is built from."""
    return {
        "obs_dim": int(np.prod(env.observation_space.shape)),
        "action_low": env.action_space.low.tolist(),
        "action_high": env.action_space.high.tolist(),
    }
