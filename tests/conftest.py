"""Shared test helpers: compose the real config with tiny overrides, temp MLflow stores, the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from mlflow.tracking import MlflowClient

from walkers import PROJECT_ROOT

CONF_DIR = str(PROJECT_ROOT / "conf")

#: Overrides that make any run tiny: short budget, quick evals, early learning.
TINY = [
    "total_steps=600",
    "eval_every=300",
    "eval_episodes=1",
    "checkpoint_every=300",
    "log_every=100",
    "progress=false",
]


def compose_cfg(overrides: list[str]):
    with initialize_config_dir(config_dir=CONF_DIR):
        return compose(config_name="train", overrides=overrides)


@pytest.fixture
def store(tmp_path):
    """A fresh sqlite MLflow store and scratch dir: overrides pointing a run at them."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    return {
        "uri": uri,
        "client": MlflowClient(uri),
        "overrides": [f"tracking.uri={uri}", f"work_dir={tmp_path / 'work'}"],
        "path": tmp_path,
    }


def run_cli(
    args: list[str], cwd: Path, timeout: float = 300, **popen
) -> subprocess.CompletedProcess:
    """``python -m walkers.train ARGS`` in a subprocess, as a user would run it."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return subprocess.run(
        [sys.executable, "-m", "walkers.train", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **popen,
    )


def spawn_cli(args: list[str], cwd: Path) -> subprocess.Popen:
    """Start ``python -m walkers.train ARGS`` in the background (to signal or kill it)."""
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    return subprocess.Popen(
        [sys.executable, "-m", "walkers.train", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for_uploaded_checkpoint(
    proc: subprocess.Popen, store_path: Path, name: str, timeout: float = 120
) -> None:
    """Block until the run has uploaded ``checkpoints/<name>`` to the store's artifacts."""
    deadline = time.monotonic() + timeout
    while not list((store_path / "mlartifacts").rglob(name)):
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.monotonic() < deadline, f"no {name} within {timeout} s"
        time.sleep(0.2)


def all_runs(client: MlflowClient) -> list:
    """Every run in every experiment of a store (empty for a store never written to)."""
    return client.search_runs([e.experiment_id for e in client.search_experiments()])


def metric_steps(client: MlflowClient, run_id: str, key: str) -> list[int]:
    return [m.step for m in client.get_metric_history(run_id, key)]
