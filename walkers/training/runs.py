"""A training run in MLflow: opened (or reopened on resume) with its config, tags and folder.

Its final status is set by :func:`walkers.tracking.ending` around the whole training, whatever
way it ends.
"""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from walkers import PROJECT_ROOT, tracking
from walkers.training.bookkeeping import RESUME_DIR
from walkers.training.resume import last_checkpoint, run_dir
from walkers.tuning.studies import redacted

log = logging.getLogger("walkers")

#: Tag: the machine (and Ray node) that trains the run; a resumed run: the latest one.
WORKER_TAG = "walkers.worker"
#: Tags of a population member's run: the population's size, the member's place in it.
POPULATION_TAG = "walkers.population"
MEMBER_TAG = "walkers.population_member"
#: Tag of an earlier attempt's run that a job run again could not continue (it is FAILED).
SUPERSEDED_TAG = "walkers.superseded"


def open_run(client, cfg: DictConfig, x_axis: str, data=None, extra_tags: dict | None = None):
    """Reopen the resumed run, or create a new one with the config as params and tags.

    ``x_axis``: what the run's steps count; ``data``: an offline run's dataset; ``extra_tags``
    are set either way (a population member: its place in the population).
    """
    spool = Path(cfg.work_dir) / "spool"
    if cfg.resume:
        tracker = tracking.Tracker.reopen(client, cfg.resume, spool, resumed_training=True)
        tracker.set_tags((extra_tags or {}) | trial_tags(cfg) | {WORKER_TAG: worker_name()})
        _start_system_metrics(tracker, cfg)
        return tracker
    algo, env_id, commit = cfg.algo.name, cfg.env.id, git_commit()
    tags = {
        "algo": algo,
        "env": env_id,
        "seed": str(cfg.seed),
        "impl": cfg.get("impl", "walkers"),
        WORKER_TAG: worker_name(),
        "git_commit": commit,
        "mlflow.source.git.commit": commit,
        tracking.X_AXIS_TAG: x_axis,
    }
    if data is not None:
        tags["dataset"] = data.id
    if cfg.job_key:
        tags[tracking.JOB_KEY_TAG] = cfg.job_key
    tags |= (extra_tags or {}) | trial_tags(cfg)
    twin = "-sb3" if cfg.get("impl") == "sb3" else ""
    run_name = cfg.tracking.run_name or f"{algo}{twin}-{env_id}-s{cfg.seed}"
    if cfg.trial.number is not None:  # a trial of an Optuna study
        run_name = f"{cfg.trial.study}-trial{cfg.trial.number}"
        if cfg.seeds_per_trial > 1:
            run_name += f"-s{cfg.seed}"
    tracker = tracking.Tracker.start(
        client, cfg.tracking.experiment, run_name=run_name, tags=tags, spool_dir=spool
    )
    try:
        tracker.log_params(tracking.flatten(shareable(cfg)))
        if data is not None:
            tracker.log_params(dataset_params(data))
    except BaseException:
        tracker.end(tracking.FAILED)
        raise
    _start_system_metrics(tracker, cfg)
    return tracker


def worker_name() -> str:
    """Where the run trains: the host, and the Ray node when a Ray cluster runs the job."""
    host = socket.gethostname()
    if "ray" in sys.modules:  # only a Ray launcher's job has it imported
        import ray

        if ray.is_initialized():
            return f"{host}/ray-node-{ray.get_runtime_context().get_node_id()[:12]}"
    return host


def shareable(cfg: DictConfig) -> dict:
    """The resolved config as MLflow params, ``config.yaml`` and checkpoints hold it: without
    the study database's password (jobs get theirs from the sweeper, never from a stored
    config)."""
    data = OmegaConf.to_container(cfg, resolve=True)
    for node in ("trial", "optuna"):
        if isinstance(data.get(node), dict) and data[node].get("storage"):
            data[node]["storage"] = redacted(data[node]["storage"])
    if isinstance(data.get("tracking"), dict) and data["tracking"].get("uri"):
        data["tracking"]["uri"] = tracking.redacted_uri(data["tracking"]["uri"])
    return data


def trial_tags(cfg: DictConfig) -> dict[str, str]:
    """A sweep job's place in its study: the study, the trial, the MLflow run it nests under
    (set again on resume: a retried trial of a study continues the run of the trial it
    retries)."""
    if cfg.trial.number is None:
        return {}
    tags = {"walkers.study": cfg.trial.study, "walkers.trial": str(cfg.trial.number)}
    if cfg.trial.parent_run_id:
        tags["mlflow.parentRunId"] = cfg.trial.parent_run_id
    return tags


def _start_system_metrics(tracker: tracking.Tracker, cfg: DictConfig) -> None:
    if cfg.tracking.get("system_metrics"):
        tracker.start_system_metrics(cfg.tracking.system_metrics_every)


def continue_earlier_attempt(client, cfg: DictConfig) -> DictConfig:
    """A job run again continues the run(s) of its earlier attempt instead of starting more.

    Ray runs a job again when its worker died (kill -9, ``ray stop`` on the node); a study runs
    a trial again when its sweeper died (``optuna.max_retry``). The earlier attempt's run, left
    RUNNING (or KILLED by SIGTERM), is found by the job's key (``job_key``) and resumed from its
    last checkpoint, fetched from MLflow on whatever worker this is; a population's K member
    runs are resumed together (``resume=[...]``). Without checkpoints to continue from (none
    yet, or a population's members cut at different steps) the earlier runs are marked FAILED
    and new ones start.
    """
    if not cfg.job_key:
        return cfg
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        return cfg
    query = tracking.tags_equal({tracking.JOB_KEY_TAG: cfg.job_key})
    earlier = [
        r
        for r in tracking.search_runs(client, experiment.experiment_id, query)
        if r.info.status in ("RUNNING", "KILLED")
    ]
    if not earlier:
        return cfg
    if cfg.population > 1:
        by_member = {int(r.data.tags.get(MEMBER_TAG, -1)): r for r in earlier}
        runs = [by_member.get(i) for i in range(cfg.population)]
    else:
        runs = earlier[:1]
    problem = _why_not_continued(client, cfg, runs)
    ids = [r.info.run_id for r in earlier if r is not None]
    if problem:
        log.warning(
            "job %s ran before as run(s) %s, %s: marked FAILED; starting anew",
            cfg.job_key,
            ", ".join(ids),
            problem,
        )
        for run_id in ids:
            tracker = tracking.Tracker.attach(client, run_id, Path(cfg.work_dir) / "spool")
            tracker.set_tags({SUPERSEDED_TAG: f"{problem}: the job ran again as new run(s)"})
            tracker.end(tracking.FAILED)
        return cfg
    log.warning(
        "job %s ran before as run(s) %s (%s): continuing it from its last checkpoint",
        cfg.job_key,
        ", ".join(ids),
        earlier[0].info.status,
    )
    cfg = cfg.copy()
    cfg.resume = ids[0] if cfg.population == 1 else [r.info.run_id for r in runs]
    return cfg


def _why_not_continued(client, cfg: DictConfig, runs: list) -> str | None:
    """Why the earlier attempt's runs (one per member, None where missing) cannot go on."""
    if any(r is None for r in runs):
        return f"which are not the {cfg.population} members of a population"
    steps = set()
    for run in runs:
        run_id = run.info.run_id
        uploaded = [a.path for a in client.list_artifacts(run_id, "checkpoints")]
        local = run_dir(cfg.work_dir, run_id) / RESUME_DIR / "last.pt"
        if "checkpoints/last.pt" not in uploaded and not local.is_file():
            return "which ended without a checkpoint"
        if len(runs) > 1:  # members continue together only from one step
            steps.add(last_checkpoint(client, run_id, cfg.work_dir)["trainer"]["step"])
    if len(steps) > 1:
        return f"whose members' checkpoints are at different steps {sorted(steps)}"
    return None


def prepare_run_dir(cfg: DictConfig, tracker: tracking.Tracker) -> Path:
    """The run's local folder, with its ``config.yaml`` written and logged."""
    folder = run_dir(cfg.work_dir, tracker.run_id)
    config_yaml = folder / "config.yaml"
    config_yaml.parent.mkdir(parents=True, exist_ok=True)
    config_yaml.write_text(OmegaConf.to_yaml(shareable(cfg)))
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
