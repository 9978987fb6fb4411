"""``python -m walkers.export``: a study's, an experiment's or a selection's runs as one bundle.

    python -m walkers.export tracking.experiment=ab_tiny study=tiny out=my_bundle
    python -m walkers.export tracking.experiment=walkers 'where={algo: td3}' checkpoints=true out=b
    python -m walkers.export ... out=results/tiny/bundle replace=true   # the same bundle, anew

The bundle's format, and why it is not mlflow-export-import's: :mod:`walkers.tracking.bundles`.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from walkers import CONF_DIR
from walkers.analysis.references import recorded_fingerprint
from walkers.cli import exit_on_bad_overrides, or_exit
from walkers.errors import ConfigError
from walkers.secrets import redacted_uri
from walkers.tracking import bundles
from walkers.tracking.client import connect

STATUSES = ("FINISHED", "KILLED", "FAILED", "RUNNING")


def export(cfg: DictConfig) -> bundles.Exported:
    checkpoints, replace = _flag(cfg.checkpoints, "checkpoints"), _flag(cfg.replace, "replace")
    statuses = list(cfg.statuses)
    bad = [s for s in statuses if s not in STATUSES]
    if bad or not statuses:
        raise ConfigError(f"statuses={statuses} is not allowed: some of {', '.join(STATUSES)}")
    where = OmegaConf.to_container(cfg.where) if cfg.where else {}
    if not isinstance(where, dict):
        raise ConfigError(f"where={where!r} is not allowed: a mapping of tags, e.g. {{algo: td3}}")
    client = connect(cfg.tracking.uri)
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        raise ConfigError(
            f"tracking.experiment={cfg.tracking.experiment!r} is not in the store "
            f"{redacted_uri(cfg.tracking.uri)}: nothing exported"
        )
    study = None if cfg.study is None else str(cfg.study)
    runs = bundles.runs_to_export(client, experiment.experiment_id, study, where, statuses)
    if not runs:
        raise ConfigError(f"no run of {cfg.tracking.experiment!r} matches: nothing exported")
    selection = f"study={study}" if study else "experiment"
    if where:
        selection += " where " + ", ".join(f"{k}={v}" for k, v in where.items())
    selection += f"; statuses {','.join(statuses)}" + ("; checkpoints" * checkpoints)
    return bundles.export_runs(
        client,
        cfg.tracking.experiment,
        runs,
        Path(cfg.out),
        selection,
        checkpoints=checkpoints,
        fingerprint=recorded_fingerprint,
        replace=replace,
    )


def _flag(value, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}={value!r} is not allowed: true or false")
    return value


@hydra.main(config_path=str(CONF_DIR), config_name="export")
def main(cfg: DictConfig) -> None:
    done = or_exit(export, cfg)
    print(f"exported {done.runs} runs to {done.path} ({done.bytes / 1024:.1f} KiB)")


if __name__ == "__main__":
    exit_on_bad_overrides("export")
    main()
