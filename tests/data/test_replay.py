"""The replay buffer of walkers/data/replay.py: a population's members sample as single buffers
of their seeds would (its counter-based streams: ``tests/test_seeding.py``), a member cut
out loads as one, and a buffer an older walkers saved still loads."""

from __future__ import annotations

import logging

import numpy as np
import torch

from walkers.data.replay import ReplayBuffer


def _filled(seeds, transitions: np.ndarray) -> ReplayBuffer:
    """A buffer of ``len(seeds)`` members; member k gets ``transitions[k]`` (steps, 3) as obs."""
    buffer = ReplayBuffer(64, 3, 1, seeds=seeds)
    for step in range(transitions.shape[1]):
        obs = transitions[:, step]
        zeros = np.zeros(len(seeds), dtype=np.float32)
        buffer.add(obs, zeros[:, None], zeros, obs + 1, zeros, zeros.astype(bool))
    return buffer


def test_a_member_samples_what_a_single_buffer_of_its_seed_samples():
    data = np.random.default_rng(0).normal(size=(3, 40, 3)).astype(np.float32)
    population, single = _filled([3, 4, 5], data), _filled([4], data[1:2])
    for _ in range(3):
        got, alone = population.sample(16), single.sample(16)
        assert got.obs.shape == (3, 16, 3) and torch.equal(got.index[1], alone.index[0])
        assert torch.equal(got.obs[1], alone.obs[0]) and torch.equal(
            got.next_obs[1], got.obs[1] + 1
        )
    # member 1 cut out is a single buffer's state, and loads as one
    cut = population.member_state_dict(1, with_data=True)
    assert cut["data"]["obs"].shape == (40, 3) and cut["sampler"]["drawn"] == 48
    again = ReplayBuffer(64, 3, 1, seeds=[9])
    again.load_state_dict(cut)
    assert torch.equal(again.sample(16).obs, single.sample(16).obs)


def test_a_buffer_saved_by_an_older_walkers_loads_and_says_its_batches_change(caplog):
    """Before the counter-based sampler a checkpoint held a torch.Generator's state."""
    old = {"pos": 5, "size": 5, "generator": torch.Generator().get_state()}
    buffer = ReplayBuffer(8, 3, 1)
    with caplog.at_level(logging.WARNING, logger="walkers"):
        buffer.load_state_dict(old)
    assert "saved by an older walkers" in caplog.text
    assert len(buffer) == 0  # no transitions in it: refilled from empty, as before
