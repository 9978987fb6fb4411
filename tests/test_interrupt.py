"""A terminated run ends KILLED with a checkpoint it can resume from."""

from __future__ import annotations

import signal

from tests.conftest import all_runs, run_cli, spawn_cli, wait_for_uploaded_checkpoint
from walkers import checkpoints


def test_sigterm_saves_a_checkpoint_and_ends_killed(store):
    args = [
        "env=pendulum",
        "total_steps=100000",
        "eval_every=500",
        "eval_episodes=1",
        "checkpoint_every=100000",
        "algo.learning_starts=100",
        "progress=false",
        *store["overrides"],
    ]
    proc = spawn_cli(args, cwd=store["path"])
    try:
        wait_for_uploaded_checkpoint(proc, store["path"], "best.pt")  # it is training
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    step = checkpoints.load(path)["trainer"]["step"]
    assert 500 <= step < 100000

    resumed = run_cli(
        [f"resume={run.info.run_id}", f"total_steps={step + 200}", *store["overrides"]],
        cwd=store["path"],
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
