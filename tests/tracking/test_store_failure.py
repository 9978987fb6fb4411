"""An MLflow server that dies mid-run: training finishes, checkpoints land, metrics are kept."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from tests.conftest import spawn_cli
from walkers.training.run import read_checkpoint

pytestmark = pytest.mark.faults  # `make test-faults`, beside `make test` in CI


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_server(path, port: int) -> subprocess.Popen:
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--backend-store-uri",
            f"sqlite:///{path / 'server.db'}",
            "--artifacts-destination",
            str(path / "server-artifacts"),
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 60
    while True:
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=1)
            return server
        except OSError:
            assert server.poll() is None and time.monotonic() < deadline, "no MLflow server"
            time.sleep(0.3)


def test_training_outlives_its_tracking_server(tmp_path, monkeypatch):
    port = _free_port()
    server = _start_server(tmp_path, port)
    work = tmp_path / "work"
    # fail fast instead of MLflow's default minutes of HTTP retries
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "3")
    monkeypatch.setenv("WALKERS_STORE_PATIENCE_S", "5")  # the server never comes back
    proc = spawn_cli(
        [
            "env=pendulum",
            "total_steps=2000",
            "eval_every=200",
            "eval_episodes=1",
            "checkpoint_every=200",
            "log_every=100",
            "algo.learning_starts=100",
            "algo.hidden_sizes=[32,32]",
            "progress=false",
            f"tracking.uri=http://127.0.0.1:{port}",
            f"work_dir={work}",
        ],
        cwd=tmp_path,
    )
    try:
        deadline = time.monotonic() + 120
        while not list(work.glob("runs/*/checkpoints/last.pt")):  # it is training and logging
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            assert time.monotonic() < deadline
            time.sleep(0.1)
        os.killpg(server.pid, 9)  # the server dies mid-run
        server.wait(timeout=30)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        proc.kill()
        if server.poll() is None:
            os.killpg(server.pid, 9)
    assert proc.returncode == 0, stderr[-3000:]  # training went on to the end
    (checkpoint,) = work.glob("runs/*/checkpoints/last.pt")
    assert read_checkpoint(checkpoint)["trainer"]["step"] == 2000  # the last checkpoint landed
    spool = checkpoint.parent.parent / "unlogged_metrics.jsonl"  # kept in the run's folder
    assert f"saved to {spool}" in stdout + stderr  # ... and the user is told where they went
    kept = [json.loads(line) for line in spool.read_text().splitlines()]
    eval_steps = {m["step"] for m in kept if m["key"] == "eval/return_mean"}
    assert 2000 in eval_steps and {"final/return_mean", "perf/sps"} <= {m["key"] for m in kept}
