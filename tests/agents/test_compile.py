"""``compile=true``: TD3/DDPG's loss computations through torch.compile compute the same update."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import TINY, all_runs, compose_cfg, filled_agent
from walkers.agents.td3 import TD3
from walkers.train import train


def filled_td3(compile: bool, population: int) -> TD3:
    """A small TD3 (or population) with the same seed and the same 200 stored transitions."""
    return filled_agent(TD3, population, compile=compile)


@pytest.mark.parametrize("population", [1, 2])
def test_compiled_updates_follow_the_eager_ones(population):
    eager, compiled = filled_td3(False, population), filled_td3(True, population)
    for _ in range(6):  # three critic-only and three actor updates (policy delay 2)
        torch.manual_seed(0)  # the same target-smoothing noise for both
        eager_metrics = eager.update()
        torch.manual_seed(0)
        compiled_metrics = compiled.update()
        for key in ("loss/critic", "train/q_mean"):
            torch.testing.assert_close(compiled_metrics[key], eager_metrics[key])
    assert "loss/actor" in compiled_metrics
    torch.testing.assert_close(compiled_metrics["loss/actor"], eager_metrics["loss/actor"])
    for name in ("actor", "critic", "actor_target", "critic_target"):
        eager_state = getattr(eager, name).state_dict()
        for key, value in getattr(compiled, name).state_dict().items():
            torch.testing.assert_close(value, eager_state[key], msg=f"{name}.{key}")
    # Moved from the start: the comparison above compares learning, not two idle agents.
    start = filled_td3(False, population).critic.state_dict()
    moved = [not torch.equal(v, start[k]) for k, v in compiled.critic.state_dict().items()]
    assert all(moved)


def test_compiled_ddpg_trains_through_the_entrypoint(store):
    overrides = ["algo=ddpg", "env=pendulum", "algo.compile=true", "algo.hidden_sizes=[32,32]"]
    overrides += ["algo.learning_starts=200", "algo.batch_size=64", *TINY, *store["overrides"]]
    train(compose_cfg(overrides))
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    assert run.data.params["algo.compile"] == "True"
    assert np.isfinite(run.data.metrics["loss/critic"])
    assert np.isfinite(run.data.metrics["loss/actor"])
