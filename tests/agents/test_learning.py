"""Agents actually learn on cheap tasks within a bounded budget."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import all_runs, compose_cfg
from walkers.train import train

pytestmark = pytest.mark.slow  # `make test-slow`, beside `make test` in CI


def learning_run(store, overrides: list[str]) -> dict[str, list[float]]:
    train(compose_cfg([*overrides, "progress=false", *store["overrides"]]))
    (run,) = all_runs(store["client"])
    history = {
        key: [m.value for m in store["client"].get_metric_history(run.info.run_id, key)]
        for key in ("eval/return_mean", "train/episode_return")
    }
    print(history["eval/return_mean"])
    return history


# A random policy scores about -1200 on Pendulum-v1; a swing-up policy about -150. TD3's learning
# test is the first step of the offline chain in test_offline.py (its run feeds the datasets).


def test_ddpg_learns_pendulum(store):
    history = learning_run(
        store,
        [
            "algo=ddpg",
            "env=pendulum",
            "seed=0",
            "total_steps=8000",
            "eval_every=2000",
            "eval_episodes=5",
            "algo.learning_starts=1000",
            "algo.hidden_sizes=[64,64]",  # like the TD3 run: learns as well, in a third of the time
            "checkpoint_every=5000",
        ],
    )["eval/return_mean"]
    assert history[0] < -900, history  # it started from a poor policy ...
    assert max(history) >= -300, history  # ... and learned to swing up


def test_reinforce_learns_inverted_pendulum(store):
    # Random actions balance the pole for ~6 steps (return ~6); the maximum is 1000.
    history = learning_run(
        store,
        [
            "algo=reinforce",
            "env=inverted_pendulum",
            "seed=0",
            "total_steps=50000",
            "eval_every=5000",
            "eval_episodes=5",
            "checkpoint_every=25000",
        ],
    )
    train_returns = history["train/episode_return"]
    first, last = np.mean(train_returns[:20]), np.mean(train_returns[-20:])
    assert last > 4 * first, (first, last)
    assert max(history["eval/return_mean"]) >= 100, history["eval/return_mean"]
