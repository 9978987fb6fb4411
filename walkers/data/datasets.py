"""Offline datasets in the Minari format: the only module that talks to Minari.

Datasets live where Minari keeps them: ``$MINARI_DATASETS_PATH`` if set, else
``~/.minari/datasets``, one folder per id (``walkers/walker2d/td3-expert-v0``). Datasets the
platform records and datasets downloaded with ``minari download mujoco/walker2d/expert-v0`` sit side
by side and load the same way. An id without a version gets ``-v0``.

Every dataset walkers writes stores two reference returns in its metadata, Minari's
``ref_min_score`` (a uniform random policy on the env) and ``ref_max_score`` (the mean episode
return of the behaviour policy, i.e. of the dataset), so a score can be normalized between them:
0 = random, 100 = as good as the data.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from walkers.data.episodes import Episode
from walkers.errors import ConfigError

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import minari
    from minari.data_collector import EpisodeBuffer

_VERSION = re.compile(r"-v\d+$")


def dataset_id(name: str) -> str:
    """``name`` as a Minari id: ``-v0`` appended when it carries no version."""
    name = str(name).strip()
    return name if _VERSION.search(name) else f"{name}-v0"


def root() -> Path:
    """The folder local datasets are kept in."""
    return Path(minari.storage.get_dataset_path())


def local_ids() -> list[str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sorted(minari.list_local_datasets())


def exists(name: str) -> bool:
    return dataset_id(name) in local_ids()


@dataclass
class OfflineData:
    """A dataset as an offline agent sees it: plain arrays, no Minari."""

    id: str
    env_id: str | None
    episodes: list[Episode]
    random_return: float | None  # ref_min_score: a uniform random policy's mean return
    behaviour_return: float | None  # ref_max_score: the data's (or the expert's) mean return

    @property
    def returns(self) -> np.ndarray:
        return np.array([e.episode_return for e in self.episodes])

    @property
    def steps(self) -> int:
        return sum(len(e.rewards) for e in self.episodes)

    @functools.cached_property
    def digest(self) -> str:
        """What the data is, not what it is called: a hash of every episode's arrays, in order
        (16 hex digits). A dataset rebuilt under its name by other runs, or on another CPU, has
        another digest; the same data rebuilt has the same."""
        hashed = hashlib.sha256()
        for e in self.episodes:
            for array in (e.observations, e.actions, e.rewards, e.terminations, e.truncations):
                hashed.update(np.ascontiguousarray(array).tobytes())
            hashed.update(b"|")  # an episode's end: the same steps cut otherwise differ
        return hashed.hexdigest()[:16]


def load_local(name: str) -> OfflineData:
    """The local dataset ``name``; if it is missing, a :class:`ConfigError` listing the others."""
    ds_id = dataset_id(name)
    available = local_ids()
    if ds_id not in available:
        raise ConfigError(
            f"dataset={name!r} is not a local Minari dataset in {root()}; "
            f"local datasets: {', '.join(available) or 'none'} "
            "(make one with `python -m walkers.collect`, or `minari download <id>`)"
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = minari.load_dataset(ds_id)
    for what, space in (("observation", ds.observation_space), ("action", ds.action_space)):
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise ConfigError(
                f"dataset={ds_id!r} has a {space} {what} space: offline agents need flat "
                "continuous (Box) observations and actions"
            )
    episodes = [
        Episode(
            observations=np.asarray(e.observations, dtype=np.float32),
            actions=np.asarray(e.actions, dtype=np.float32),
            rewards=np.asarray(e.rewards, dtype=np.float64),
            terminations=np.asarray(e.terminations, dtype=bool),
            truncations=np.asarray(e.truncations, dtype=bool),
        )
        for e in ds.iterate_episodes()
    ]
    meta = ds.storage.metadata
    spec = ds.env_spec
    return OfflineData(
        id=ds_id,
        env_id=spec.id if spec is not None else None,
        episodes=episodes,
        random_return=meta.get("ref_min_score"),
        behaviour_return=meta.get("ref_max_score"),
    )


def plain_spec(env: gym.Env) -> gym.envs.registration.EnvSpec:
    """``env``'s spec (id, time limit, kwargs) without walkers' wrappers or a render mode."""
    spec = env.spec
    kwargs = {k: v for k, v in spec.kwargs.items() if k != "render_mode"}
    return dataclasses.replace(spec, additional_wrappers=(), kwargs=kwargs)


def write(
    name: str,
    episodes: list[Episode],
    env: gym.Env,
    *,
    algorithm: str,
    description: str,
    random_return: float,
    overwrite: bool = False,
) -> OfflineData:
    """Store ``episodes`` (recorded on ``env``) as the Minari dataset ``name``."""
    ds_id = dataset_id(name)
    if not episodes:
        raise ConfigError(f"dataset={ds_id!r}: no complete episodes to store")
    if exists(ds_id):
        if not overwrite:
            raise ConfigError(
                f"dataset={ds_id!r} already exists in {root()}: "
                "choose another name or version, or pass overwrite=true"
            )
        minari.delete_dataset(ds_id)
    behaviour = float(np.mean([e.episode_return for e in episodes]))
    buffers = [
        EpisodeBuffer(
            id=i,
            observations=e.observations,
            actions=e.actions,
            rewards=e.rewards,
            terminations=e.terminations,
            truncations=e.truncations,
        )
        for i, e in enumerate(episodes)
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Minari nags about unset author e-mail and permalink
        minari.create_dataset_from_buffers(
            ds_id,
            buffers,
            env=plain_spec(env),
            algorithm_name=algorithm,
            author="walkers",
            description=description,
            ref_min_score=float(random_return),
            ref_max_score=behaviour,
        )
    return load_local(ds_id)
