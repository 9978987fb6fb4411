"""A training run in MLflow: opened (or reopened on resume) with its config, tags and folder.

Its final status is set by :func:`walkers.tracking.ending` around the whole training, whatever
way it ends.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from walkers import PROJECT_ROOT, tracking
from walkers.training.resume import run_dir


def open_run(client, cfg: DictConfig, x_axis: str, data=None, extra_tags: dict | None = None):
    """Reopen the resumed run, or create a new one with the config as params and tags.

    ``x_axis``: what the run's steps count; ``data``: an offline run's dataset; ``extra_tags``
    are set either way (a population member: its place in the population).
    """
    spool = Path(cfg.work_dir) / "spool"
    if cfg.resume:
        tracker = tracking.Tracker.reopen(client, cfg.resume, spool)
        if extra_tags:
            tracker.set_tags(extra_tags)
        return tracker
    algo, env_id, commit = cfg.algo.name, cfg.env.id, git_commit()
    tags = {
        "algo": algo,
        "env": env_id,
        "seed": str(cfg.seed),
        "git_commit": commit,
        "mlflow.source.git.commit": commit,
        tracking.X_AXIS_TAG: x_axis,
    }
    if data is not None:
        tags["dataset"] = data.id
    tags |= extra_tags or {}
    run_name = cfg.tracking.run_name or f"{algo}-{env_id}-s{cfg.seed}"
    if cfg.trial.number is not None:  # a trial of an Optuna study
        tags |= {"walkers.study": cfg.trial.study, "walkers.trial": str(cfg.trial.number)}
        run_name = f"{cfg.trial.study}-trial{cfg.trial.number}"
        if cfg.trial.parent_run_id:
            tags["mlflow.parentRunId"] = cfg.trial.parent_run_id
    tracker = tracking.Tracker.start(
        client, cfg.tracking.experiment, run_name=run_name, tags=tags, spool_dir=spool
    )
    try:
        tracker.log_params(tracking.flatten(OmegaConf.to_container(cfg, resolve=True)))
        if data is not None:
            tracker.log_params(dataset_params(data))
    except BaseException:
        tracker.end(tracking.FAILED)
        raise
    return tracker


def prepare_run_dir(cfg: DictConfig, tracker: tracking.Tracker) -> Path:
    """The run's local folder, with its ``config.yaml`` written and logged."""
    folder = run_dir(cfg.work_dir, tracker.run_id)
    config_yaml = folder / "config.yaml"
    config_yaml.parent.mkdir(parents=True, exist_ok=True)
    config_yaml.write_text(OmegaConf.to_yaml(cfg, resolve=True))
    tracker.log_artifact(config_yaml)
    return folder


def git_commit() -> str:
    """The commit the code runs from (provenance tag), or "unknown"."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=PROJECT_ROOT,
            capture_output=True,
            text=True,
            timeout=5,
        )
        return out.stdout.strip() if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def dataset_params(data) -> dict[str, str]:
    """An offline run's dataset statistics, as params."""
    returns = data.returns
    return {
        "dataset_stats.episodes": len(data.episodes),
        "dataset_stats.steps": data.steps,
        "dataset_stats.return_mean": f"{returns.mean():.2f}",
        "dataset_stats.return_max": f"{returns.max():.2f}",
        "dataset_stats.behaviour_return": data.behaviour_return,
        "dataset_stats.random_return": data.random_return,
    }
