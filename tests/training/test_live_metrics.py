"""Runs are watched live: metrics reach MLflow at every evaluation (not only at checkpoints), a
crashed run resumed from its older checkpoint logs no step twice, and system metrics fill the
run's System metrics tab."""

from __future__ import annotations

import signal
import time
from collections import Counter

import pytest

from tests.conftest import TINY, run_cli, spawn_cli

# Evaluations every 200 steps, checkpoints only every 1,000: the UI must move between them.
LIVE = [
    "algo=td3",
    "env=pendulum",
    "algo.hidden_sizes=[32,32]",
    "env.learning_starts=100",
    "total_steps=100000",  # killed long before
    "eval_every=200",
    "eval_episodes=1",
    "checkpoint_every=1000",
    "log_every=100",
    "progress=false",
    "tracking.system_metrics_every=1",
]


def _training_run(client):
    (run,) = client.search_runs(
        [e.experiment_id for e in client.search_experiments()], "tags.algo = 'td3'"
    )
    return run


@pytest.mark.slow  # `make test-slow`
def test_metrics_arrive_at_each_evaluation_and_a_crashed_run_resumes_without_logging_twice(store):
    client = store["client"]
    proc = spawn_cli([*LIVE, *store["overrides"]], cwd=store["path"])
    try:
        # Live: eval/return_mean of step 400 reaches MLflow while no checkpoint exists yet.
        deadline = time.monotonic() + 180
        while True:
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            assert time.monotonic() < deadline, "no evaluation reached MLflow in time"
            runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
            steps = [
                m.step
                for r in runs
                for m in client.get_metric_history(r.info.run_id, "eval/return_mean")
            ]
            # evaluated past the last checkpoint, and the run's mark says so too (the mark is
            # set right after the metrics: reading between the two would see the older mark)
            marks = [int(r.data.tags.get("walkers.logged_through", 0)) for r in runs]
            if len(steps) >= 6 and max(steps) % 1000 and max(marks, default=0) % 1000:
                break
            time.sleep(0.3)
        proc.send_signal(signal.SIGKILL)  # a crash: no last checkpoint, the run left RUNNING
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    run = _training_run(client)
    assert run.info.status == "RUNNING"
    logged_through = int(run.data.tags["walkers.logged_through"])
    checkpoint = logged_through // 1000 * 1000
    assert logged_through > checkpoint >= 1000  # the UI saw evaluations beyond the checkpoint
    before = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]

    # Resumed from the checkpoint: the steps up to the mark are not logged again.
    resumed = run_cli(
        [f"resume={run.info.run_id}", f"total_steps={checkpoint + 1400}", *store["overrides"]],
        cwd=store["path"],
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resumes from its checkpoint at step {checkpoint}" in resumed.stdout + resumed.stderr
    run = client.get_run(run.info.run_id)
    assert run.info.status == "FINISHED"
    for key in ("eval/return_mean", "train/episode_return", "loss/critic"):
        steps = [m.step for m in client.get_metric_history(run.info.run_id, key)]
        assert not [s for s, n in Counter(steps).items() if n > 1], f"{key} logged twice"
    steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]
    assert steps[: len(before)] == before and steps[-1] == checkpoint + 1400
    assert "final/return_mean" in run.data.metrics

    # MLflow's own monitor sampled the process every second into the System metrics tab.
    system = [k for k in run.data.metrics if k.startswith("system/")]
    assert "system/cpu_utilization_percentage" in system
    assert "system/system_memory_usage_megabytes" in system


def test_system_metrics_can_be_turned_off(store):
    result = run_cli(
        ["algo=reinforce", "env=pendulum", *TINY, "tracking.system_metrics=false",
         *store["overrides"]],
        cwd=store["path"],
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    run = _training_run_any(store["client"])
    assert not [k for k in run.data.metrics if k.startswith("system/")]


def _training_run_any(client):
    (run,) = client.search_runs([e.experiment_id for e in client.search_experiments()])
    return run
