"""``compile=true`` through the entrypoint: a compiled DDPG trains and logs its losses. That a
compiled update equals the eager one is tested for every algorithm that declares ``compile`` in
``test_shared_properties.py``."""

from __future__ import annotations

import numpy as np

from tests.conftest import TINY, all_runs, compose_cfg
from walkers.train import train


def test_compiled_ddpg_trains_through_the_entrypoint(store):
    overrides = ["algo=ddpg", "env=pendulum", "algo.compile=true", "algo.hidden_sizes=[32,32]"]
    overrides += ["algo.learning_starts=200", "algo.batch_size=64", *TINY, *store["overrides"]]
    train(compose_cfg(overrides))
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    assert run.data.params["algo.compile"] == "True"
    assert np.isfinite(run.data.metrics["loss/critic"])
    assert np.isfinite(run.data.metrics["loss/actor"])
