"""``python -m walkers.dashboard``: optuna-dashboard on the study storage the sweeps use, the way
``make ui`` serves MLflow.

    python -m walkers.dashboard                      # optuna=sqlite: ./optuna.db
    python -m walkers.dashboard optuna=postgres      # $WALKERS_OPTUNA_STORAGE
    python -m walkers.dashboard port=8081 host=0.0.0.0

The storage is read from the config (``conf/optuna/``), so a database password given as
``WALKERS_OPTUNA_STORAGE`` stays in the environment: never on a command line (``ps``), a log line
or a file. The address printed has the password redacted.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.cli import exit_on_bad_overrides, or_exit
from walkers.errors import ConfigError
from walkers.tuning.studies import absolute_storage, redacted


def serve(cfg: DictConfig) -> None:
    storage = cfg.optuna.storage
    if not storage:
        raise ConfigError(
            "optuna=postgres needs its database: export WALKERS_OPTUNA_STORAGE="
            "'postgresql+psycopg://<user>:<password>@<host>/<database>' (`make stack` prints one)"
        )
    try:
        import optuna_dashboard
    except ImportError:
        raise ConfigError(
            "optuna-dashboard is not installed: pip install -e '.[dashboard]' (make install has it)"
        ) from None
    storage = absolute_storage(storage)
    if storage.startswith("sqlite:///") and not Path(storage.removeprefix("sqlite:///")).is_file():
        raise ConfigError(
            f"optuna.storage={storage!r} has no studies yet (no such file): run a sweep first "
            "(python -m walkers.train -m sweeps=pendulum_tiny), or pass optuna=postgres"
        )
    print(f"studies in {redacted(storage)}: http://{cfg.host}:{cfg.port}", file=sys.stderr)
    optuna_dashboard.run_server(storage, host=cfg.host, port=cfg.port)


@hydra.main(config_path=str(CONF_DIR), config_name="dashboard")
def main(cfg: DictConfig) -> None:
    or_exit(serve, cfg)


if __name__ == "__main__":
    exit_on_bad_overrides("dashboard")
    main()
