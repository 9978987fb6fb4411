"""A terminated run ends KILLED with a checkpoint it can resume from."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from tests.conftest import all_runs, run_cli
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
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "walkers.train", *args],
        cwd=store["path"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # wait until it is training (a best.pt exists)
            if list((store["path"] / "work" / "runs").glob("*/checkpoints/best.pt")):
                break
            time.sleep(0.5)
        else:
            raise AssertionError("training never started")
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
