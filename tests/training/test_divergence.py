"""A run whose losses stay NaN ends FAILED with its last good checkpoint intact."""

from __future__ import annotations

import math

import gymnasium as gym
import pytest
import torch

from tests.conftest import all_runs, compose_cfg
from walkers.train import train
from walkers.training.bookkeeping import TrainingDiverged
from walkers.training.run import read_checkpoint


class NaNRewardsAfter(gym.Wrapper):
    """Pendulum whose rewards become NaN after ``start`` steps (counted across episodes)."""

    def __init__(self, start: int = 150, **kwargs):
        super().__init__(gym.make("Pendulum-v1", **kwargs))
        self.start, self.t = start, 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.t += 1
        return obs, math.nan if self.t > self.start else reward, terminated, truncated, info


gym.register("NaNRewardsPendulum-v0", entry_point=NaNRewardsAfter)


def test_persistent_nan_losses_end_the_run_failed_keeping_the_last_good_checkpoint(store):
    cfg = compose_cfg(
        [
            "algo=td3",
            "env=pendulum",
            "env.id=NaNRewardsPendulum-v0",
            "total_steps=1000",
            "eval_every=500",
            "eval_episodes=1",
            "checkpoint_every=100",
            "log_every=100",
            "algo.learning_starts=100",
            "divergence_patience=50",
            "progress=false",
            *store["overrides"],
        ]
    )
    # Updates start once 256 transitions are stored; from then on every batch holds a NaN reward,
    # so every update is skipped: 45 in a row at the log of step 300, 145 at step 400.
    with pytest.raises(TrainingDiverged) as error:
        train(cfg)
    message = str(error.value)
    assert "diverged at step 400" in message and "loss/critic=nan" in message
    assert "(step 300)" in message
    (run,) = all_runs(store["client"])
    assert run.info.status == "FAILED"
    assert run.data.metrics["health/skipped_updates"] >= 50
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    state = read_checkpoint(path)
    assert state["trainer"]["step"] == 300
    for name in ("actor", "critic"):  # the guard kept NaN out of the weights
        assert all(torch.isfinite(w).all() for w in state["agent"][name].values())
