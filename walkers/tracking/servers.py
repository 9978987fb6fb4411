"""The shared stores of a team or a cluster, started locally: PostgreSQL and an MLflow server.

``make stack`` (``python -m walkers.stack``) and the cluster tests start them with these
functions. PostgreSQL is the ``pgserver`` wheel (a real PostgreSQL 16 from pip that runs as
root, which plain ``postgres`` refuses), listening on a unix socket in its data folder; it holds
two databases, ``mlflow`` (the tracking server's backend store) and ``optuna`` (the studies).
The MLflow server serves artifacts itself (``--serve-artifacts``), so a client needs only its URL
and workers share no filesystem with it.
"""

from __future__ import annotations

import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

DATABASES = ("mlflow", "optuna")


def sqlalchemy_uri(pg_uri: str) -> str:
    """pgserver's ``postgresql://...`` as SQLAlchemy's psycopg 3 URL (what MLflow and Optuna
    take): ``postgresql+psycopg://...``."""
    return pg_uri.replace("postgresql://", "postgresql+psycopg://", 1)


def start_postgres(data_dir: Path, keep_running: bool = False):
    """PostgreSQL on ``data_dir`` (created if new), with the ``mlflow`` and ``optuna`` databases.

    Returns ``(server, {database: uri})``. The server stops when the last process holding it
    exits, unless ``keep_running``.
    """
    import pgserver  # only the stack needs it

    data_dir = Path(data_dir).resolve()
    data_dir.mkdir(parents=True, exist_ok=True)
    server = pgserver.get_server(data_dir, cleanup_mode=None if keep_running else "stop")
    existing = server.psql("SELECT datname FROM pg_database;")
    for name in DATABASES:
        if f" {name}\n" not in existing:
            server.psql(f"CREATE DATABASE {name};")
    return server, {name: sqlalchemy_uri(server.get_uri(name)) for name in DATABASES}


@dataclass
class MlflowServer:
    process: subprocess.Popen
    url: str
    log_path: Path

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def start_mlflow_server(
    backend_uri: str,
    artifacts_dir: Path,
    port: int,
    host: str = "127.0.0.1",
    log_dir=None,
    workers: int | None = None,
) -> MlflowServer:
    """``mlflow server`` on ``backend_uri`` serving artifacts from ``artifacts_dir``; returns
    once it answers ``/health`` (a first start migrates the database: ~10-20 s).

    ``workers``: its request-handling processes (None: MLflow's default, 4); a test on a small
    machine runs one, which leaves the cores to the jobs and the cluster's control plane."""
    artifacts_dir = Path(artifacts_dir).resolve()
    log_path = Path(log_dir or artifacts_dir.parent) / f"mlflow-server-{port}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    command = [
        sys.executable, "-m", "mlflow", "server",
        "--backend-store-uri", backend_uri,
        "--artifacts-destination", str(artifacts_dir),
        "--serve-artifacts",
        "--host", host,
        "--port", str(port),
        *(["--workers", str(workers)] if workers else []),
    ]  # fmt: skip
    with log_path.open("ab") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://{'127.0.0.1' if host == '0.0.0.0' else host}:{port}"
    server = MlflowServer(process, url, log_path)
    try:
        wait_for_http(f"{url}/health", timeout=120, process=process)
    except BaseException:
        server.stop()
        raise
    return server


def wait_for_http(url: str, timeout: float, process: subprocess.Popen | None = None) -> None:
    """Until ``url`` answers 200; a ``process`` that exits first is an error."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            raise RuntimeError(f"the server exited with {process.returncode} before {url} answered")
        try:
            with urllib.request.urlopen(url, timeout=2) as response:
                if response.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise TimeoutError(f"{url} did not answer within {timeout:.0f} s")
