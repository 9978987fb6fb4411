"""Agents actually learn on cheap tasks within a bounded budget."""

from __future__ import annotations

from tests.conftest import all_runs, compose_cfg
from walkers.train import train


def test_td3_learns_pendulum(store):
    # A random policy scores about -1200 on Pendulum-v1; a swing-up policy about -150.
    cfg = compose_cfg([
        "algo=td3", "env=pendulum", "seed=0", "total_steps=12000", "eval_every=2000",
        "eval_episodes=5", "algo.learning_starts=1000", "checkpoint_every=6000",
        "progress=false", *store["overrides"],
    ])
    train(cfg)
    (run,) = all_runs(store["client"])
    history = [m.value for m in store["client"].get_metric_history(run.info.run_id, "eval/return_mean")]
    assert history[0] < -900, history  # it started from a poor policy ...
    assert max(history) >= -300, history  # ... and learned to swing up
