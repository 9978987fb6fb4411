"""``compile=true`` through the entrypoint: a compiled DDPG trains, logs its losses and is
continued by ``resume=`` (on the CPU its whole update is compiled, its Adam state the
checkpoint's); a process that builds compiled agent after agent compiles each. That a compiled
update equals the eager one is tested for every algorithm that declares ``compile`` in
``test_shared_properties.py``."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from tests.conftest import TINY, all_runs, compose_cfg, filled_agent
from walkers.agents.td3 import TD3
from walkers.train import train
from walkers.training.run import read_checkpoint


def test_compiled_ddpg_trains_through_the_entrypoint_and_continues(store, caplog):
    overrides = ["algo=ddpg", "env=pendulum", "algo.compile=true", "algo.hidden_sizes=[32,32]"]
    overrides += ["algo.learning_starts=200", "algo.batch_size=64", *TINY, *store["overrides"]]
    with caplog.at_level(logging.INFO, logger="walkers"):
        train(compose_cfg(overrides))
    said = [r.getMessage() for r in caplog.records if "compiling the update" in r.getMessage()]
    assert len(said) == 1  # the wait at the first update is said, once
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    assert run.data.params["algo.compile"] == "True"
    assert np.isfinite(run.data.metrics["loss/critic"])
    assert np.isfinite(run.data.metrics["loss/actor"])

    # the second run: the same run continued from its checkpoint, its Adam moments included
    again = [f"resume={run.info.run_id}", "total_steps=900", *store["overrides"]]
    train(compose_cfg(again), again)
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    state = read_checkpoint(path)
    assert state["trainer"]["step"] == 900
    moments = state["agent"]["critic_optimizer"]["state"][0]
    assert moments["step"].item() == 900 - 200 + 1  # a critic update a step from step 200 on
    assert np.isfinite(run.data.metrics["loss/critic"])


@pytest.mark.slow
def test_agent_after_agent_in_one_process_each_runs_compiled():
    """Dynamo compiles anew for each agent, and refuses (``fullgraph``: else it would run
    eagerly) past 8 compilations of one function: ten agents in turn, as a multirun's jobs in
    one process, each through both ways of its update (with and without the actor's step)."""
    for _ in range(10):
        agent = filled_agent(TD3, compile=True)
        metrics = [agent.update() for _ in range(2)]
        assert "loss/actor" in metrics[1] and np.isfinite(metrics[1]["loss/actor"].item())
