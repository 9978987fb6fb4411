"""``python -m walkers.stack`` (``make stack``): PostgreSQL and an MLflow server on it, for a team
or a test, until Ctrl-C.

    python -m walkers.stack [--dir .walkers/stack] [--port 5000] [--host 127.0.0.1]

Prints the two URIs to use (``tracking=server`` and ``optuna=postgres`` read them from the
environment). Data persist in ``--dir``: stopping and starting again keeps every run and study.
"""

from __future__ import annotations

import argparse
import signal
import socket
import sys
import time
import warnings
from pathlib import Path

from walkers.tracking.servers import start_mlflow_server, start_postgres


def port_in_use(host: str, port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1" if host == "0.0.0.0" else host, port)) == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m walkers.stack", description=__doc__)
    parser.add_argument("--dir", default=".walkers/stack", help="data folder (kept between runs)")
    parser.add_argument("--port", type=int, default=5000, help="the MLflow server's port")
    parser.add_argument("--host", default="127.0.0.1", help="0.0.0.0: reachable from other hosts")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill`: stop both, like Ctrl-C
    warnings.filterwarnings("ignore", message="XDG_RUNTIME_DIR")  # pgserver's runtime folder
    if port_in_use(args.host, args.port):
        print(f"error: --port={args.port} is in use: pass another (--port / MLFLOW_PORT=...)",
              file=sys.stderr)  # fmt: skip
        return 2
    folder = Path(args.dir).resolve()
    server, uris = start_postgres(folder / "postgres")
    mlflow = start_mlflow_server(
        uris["mlflow"], folder / "artifacts", args.port, args.host, log_dir=folder
    )
    print(
        f"PostgreSQL 16 in {folder / 'postgres'} (unix socket), databases mlflow and optuna\n"
        f"MLflow server {mlflow.url} (artifacts in {folder / 'artifacts'}, log {mlflow.log_path})"
        "\n\nIn the shell that trains or sweeps:\n"
        f"  export MLFLOW_TRACKING_URI={mlflow.url}\n"
        f"  export WALKERS_OPTUNA_STORAGE='{uris['optuna']}'\n"
        "  python -m walkers.train -m sweeps=pendulum_tiny tracking=server optuna=postgres\n\n"
        f"MLflow UI: {mlflow.url}   Ctrl-C stops the stack (the data stay in {folder}).",
        flush=True,
    )
    try:
        while mlflow.process.poll() is None:
            time.sleep(1)
        print(f"error: the MLflow server exited; see {mlflow.log_path}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    finally:
        mlflow.stop()
        server.cleanup()


if __name__ == "__main__":
    sys.exit(main())
