"""A seeded fingerprint of an algorithm's update: what makes a stored run comparable with today's.

A run records, when it starts, the digest of the code that trains it (tag
``walkers.code_digest``: the source of ``walkers.agents`` and ``walkers.data`` and the torch
version), which costs nothing. Its export (:mod:`walkers.export`) computes the fingerprint of the
run's algorithm config where the exporting code is the code that trained it, and the bundle
keeps it with the run. A reference arm (runs from a bundle, compared without being rerun) is
used only if today's code gives the same fingerprint for the same config: the same update, so
its seeds are samples of the arm a rerun would give.

The fingerprint drives the agent, built on the CPU from the config with a fixed seed, through a
fixed stream of synthetic transitions (a 3-d observation, a 1-d action, episodes of 40 steps)
until it has made :data:`UPDATES` updates (past its warm-up, whatever its ``learning_starts``
or rollout length), then reads its greedy actions on fixed observations. Its numbers (the
losses of each update and those actions, 6 significant digits) are compared with a relative
tolerance, as CPUs differ in their last float bits; a changed loss, target, optimizer or order
of random draws moves them far more.

The global random streams are saved and restored around it: computing a fingerprint changes
nothing in the run that records it. A cache (``$XDG_CACHE_HOME/walkers``, else
``~/.cache/walkers``), keyed by the config, the source of ``walkers.agents`` and
``walkers.data`` and the torch version, keeps it to once per config and code.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import random
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
import yaml
from omegaconf import OmegaConf

from walkers.agents.base import Transition
from walkers.agents.declarations.schemas import declared_since
from walkers.agents.factory import build_agent
from walkers.errors import ConfigError
from walkers.training.provenance import CODE_DIGEST_TAG, code_digest

#: Updates the fingerprint reads.
UPDATES = 3
#: How far the numbers of the same update may differ between machines.
RELATIVE_TOLERANCE = 1e-3
_OBS_DIM, _EPISODE = 3, 40
_PROBES = np.random.default_rng(1).normal(size=(4, _OBS_DIM)).astype(np.float32)


class NoFingerprint(Exception):
    """An algorithm whose update cannot be driven by synthetic transitions (offline agents)."""


def update_fingerprint(algo: Mapping) -> list[float]:
    """The fingerprint of ``algo`` (a run's ``algo`` config) under today's code (cached)."""
    algo = OmegaConf.to_container(algo, resolve=True) if OmegaConf.is_config(algo) else dict(algo)
    algo = declared_since(algo) | algo  # a run from before a hyperparameter: its default's update
    for key in ("compile", "capture"):  # the same maths, compiled: not part of what it computes
        if key in algo:
            algo[key] = False
    key = hashlib.sha256(json.dumps([algo, code_digest()], sort_keys=True).encode()).hexdigest()[
        :24
    ]
    cached = _cache_dir() / f"{key}.json"
    if cached.is_file():
        with contextlib.suppress(ValueError, OSError):
            return json.loads(cached.read_text())
    with _rngs_kept():
        numbers = _compute(algo)
    with contextlib.suppress(OSError):  # a read-only home: computed again next time
        cached.parent.mkdir(parents=True, exist_ok=True)
        tmp = cached.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(numbers))
        tmp.replace(cached)
    return numbers


def of_run(tags: Mapping[str, str], config: str | None) -> list[float] | None:
    """The fingerprint of a run trained by this very code (its ``walkers.code_digest`` tag is
    today's) from its ``config.yaml``; None where it cannot be had here: another code trained
    it, it is a twin (``impl=sb3``), or it learns offline (built from a dataset)."""
    if config is None or tags.get(CODE_DIGEST_TAG) != code_digest():
        return None
    if tags.get("impl", "walkers") != "walkers":
        return None
    algo = (yaml.safe_load(config) or {}).get("algo")
    if not isinstance(algo, dict):
        return None
    try:
        return update_fingerprint(algo)
    except (NoFingerprint, ConfigError):
        return None


def differs(recorded: list[float], now: list[float]) -> str | None:
    """None when two fingerprints agree; else where they first differ, in words."""
    if len(recorded) != len(now):
        return f"{len(recorded)} numbers recorded, {len(now)} now"
    for i, (a, b) in enumerate(zip(recorded, now, strict=True)):
        if not np.isclose(a, b, rtol=RELATIVE_TOLERANCE, atol=1e-6):
            return f"number {i}: {a:.6g} recorded, {b:.6g} now"
    return None


def _compute(algo: dict) -> list[float]:
    cfg = OmegaConf.create({"algo": algo, "device": "cpu", "seed": 0, "impl": "walkers"})
    agent = build_agent(cfg, {"obs_dim": _OBS_DIM, "action_low": [-2.0], "action_high": [2.0]})
    if agent.offline:
        raise NoFingerprint(f"{algo.get('name')} learns offline, from a dataset")
    if agent.several_envs and agent.num_envs > 1:
        return _several_envs(agent)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=_OBS_DIM).astype(np.float32)
    numbers: list[float] = []
    updates, steps = 0, 0
    limit = int(algo.get("learning_starts", 0) or 0) + 20_000
    while updates < UPDATES and steps < limit:
        action = np.asarray(agent.act(obs, explore=True), dtype=np.float32)
        next_obs = (0.9 * obs + 0.1 * rng.normal(size=_OBS_DIM)).astype(np.float32)
        reward = float(-(obs**2).sum() - 0.1 * (action**2).sum())
        steps += 1
        end = steps % _EPISODE == 0
        agent.observe(Transition(obs, action, reward, next_obs, False, end))
        losses = agent.update()
        if losses:
            updates += 1
            numbers += [float(losses[k]) for k in sorted(losses)]
        obs = rng.normal(size=_OBS_DIM).astype(np.float32) if end else next_obs
    numbers += [float(x) for probe in _PROBES for x in np.ravel(agent.act(probe, explore=False))]
    return [float(f"{x:.6g}") for x in numbers]


def _several_envs(agent) -> list[float]:
    """:func:`_compute`'s synthetic task on ``agent.num_envs`` envs acting as one batch (each its
    own stream of states, the episodes ending together)."""
    n, rng = agent.num_envs, np.random.default_rng(0)
    obs = rng.normal(size=(n, _OBS_DIM)).astype(np.float32)
    numbers: list[float] = []
    updates, steps = 0, 0
    while updates < UPDATES and steps < 20_000 * n:
        actions = np.asarray(agent.act(obs, explore=True), dtype=np.float32)
        next_obs = (0.9 * obs + 0.1 * rng.normal(size=obs.shape)).astype(np.float32)
        rewards = -(obs**2).sum(axis=1) - 0.1 * (actions**2).sum(axis=1)
        steps += n
        end = (steps // n) % _EPISODE == 0
        agent.observe_batch(
            [
                Transition(obs[i], actions[i], float(rewards[i]), next_obs[i], False, end)
                for i in range(n)
            ]  # fmt: skip
        )
        if losses := agent.update():
            updates += 1
            numbers += [float(losses[k]) for k in sorted(losses)]
        obs = rng.normal(size=obs.shape).astype(np.float32) if end else next_obs
    numbers += [float(x) for probe in _PROBES for x in np.ravel(agent.act(probe, explore=False))]
    return [float(f"{x:.6g}") for x in numbers]


@contextlib.contextmanager
def _rngs_kept():
    """Every global random stream as it was, whatever the fingerprint drew."""
    state = random.getstate(), np.random.get_state()
    with torch.random.fork_rng(devices=[]):
        try:
            yield
        finally:
            random.setstate(state[0])
            np.random.set_state(state[1])


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "walkers" / "fingerprints"
