"""A study's MLflow runs: the study's parent run (reopened when the study resumes), a trial's
own run when it has several seeds (nested between the two), the best trial on the parent, and
the runs of a batch whose launch failed, ended.
"""

from __future__ import annotations

import logging
from pathlib import Path

import optuna
from omegaconf import DictConfig, OmegaConf
from optuna.trial import TrialState

from walkers.secrets import redacted
from walkers.tracking.client import Tracker, end_running, tags_equal
from walkers.tracking.hydra_callbacks import stop_remote_jobs
from walkers.tracking.names import JOB_KEY_TAG, KIND_TAG, status_after
from walkers.tuning.objective import DONE, trials_done
from walkers.tuning.optuna_internals import stored_trial
from walkers.tuning.studies import original_number

log = logging.getLogger("walkers")

STUDY_TAG = "walkers.study"
#: Trial run tag: the trial a retried trial repeats (its own number if it is no retry).
ORIGINAL_TRIAL_TAG = "walkers.original_trial"


def end_jobs_runs(client, experiment: str, job_keys: list[str], error: BaseException) -> None:
    """A batch whose launcher failed (a job's retries ran out on a cluster, Ctrl-C of the
    sweeper): its jobs still out there are stopped (a Ray driver's tasks end with it) and their
    runs left RUNNING are ended, KILLED after Ctrl-C, else FAILED, with the reason as a tag."""
    stop_remote_jobs()
    status = status_after(error)
    reason = f"its batch's launch ended: {type(error).__name__}: {error}"
    try:
        for key in job_keys:
            query = tags_equal({JOB_KEY_TAG: key})
            for run_id in end_running(client, experiment, query, status, reason):
                log.warning("run %s of job %s was left RUNNING: %s", run_id, key, status)
    except Exception as e:  # the launcher's error is the one to report
        log.error("could not end the runs of the failed batch: %s", e)


def log_best(
    parent: Tracker, study: optuna.Study, best: optuna.trial.FrozenTrial, results: Path
) -> None:
    """The best trial on the study's parent run, in forms a resumed study may change.

    MLflow params never change once logged, so the best values are tags (``best.<param>``) and
    metrics (``best_value``, ``best_trial``, at step = trials done: their history is how the
    best improved as the study grew), plus the ``optimization_results.yaml`` artifact.
    """
    parent.set_tags({f"best.{k}": v for k, v in best.params.items()})
    parent.log_metrics(
        {"best_value": best.value, "best_trial": best.number}, step=trials_done(study)
    )
    parent.log_artifact(results)
    log.info("MLflow parent run: %s", parent.url)


def open_trial_run(
    parent: Tracker | None, study: optuna.Study, trial: optuna.Trial
) -> Tracker | None:
    """A trial's own MLflow run (``seeds_per_trial`` > 1): its parameters and outcome, nested
    under the study's run, its seeds' runs nested under it. A retry of a dead sweeper's trial
    takes over the run of the trial it retries (as its seeds' jobs continue theirs)."""
    if parent is None:
        return None
    original = original_number(stored_trial(study, trial))
    tags = {
        KIND_TAG: "trial",
        STUDY_TAG: study.study_name,
        "walkers.trial": str(trial.number),
        ORIGINAL_TRIAL_TAG: str(original),
        "mlflow.parentRunId": parent.run_id,
    }
    experiment = parent.client.get_experiment(parent.experiment_id).name
    name = f"{study.study_name}-trial{trial.number}"
    if original == trial.number:  # a first attempt: a run of its own
        return Tracker.start(parent.client, experiment, name, tags, parent.spool_dir)
    query = tags_equal(  # a retry: the run of the trial it repeats
        {KIND_TAG: "trial", STUDY_TAG: study.study_name, ORIGINAL_TRIAL_TAG: original}
    )
    return Tracker.reopen_or_start(parent.client, experiment, query, name, tags, parent.spool_dir)


def log_trial_outcome(run: Tracker, study: optuna.Study, trial: optuna.Trial, metric: str) -> None:
    """The trial's sampled parameters, state and value (the mean over its seeds) on its run."""
    frozen = stored_trial(study, trial)
    run.log_params({k: str(v) for k, v in frozen.params.items()})
    run.set_tags({"walkers.trial_state": frozen.state.name})
    if frozen.value is not None:
        run.log_metrics({metric: frozen.value}, step=0)


def open_parent_run(
    client, config: DictConfig, study: optuna.Study, storage: str | None
) -> Tracker:
    """The study's MLflow parent run: reopened when a study is resumed, else created."""
    tags = {
        KIND_TAG: "study",
        STUDY_TAG: study.study_name,
        "optuna.storage": str(redacted(storage)),
        "walkers.optimized_metric": config.optimized_metric,
        "walkers.direction": study.direction.name.lower(),
    }
    query = tags_equal({KIND_TAG: "study", STUDY_TAG: study.study_name})
    return Tracker.reopen_or_start(
        client,
        config.tracking.experiment,
        query,
        f"study-{study.study_name}",
        tags,  # also given to a study's run from before these tags existed
        Path(config.work_dir) / "spool",
    )


def report_best(
    study: optuna.Study,
    fixed: dict,
    parent: Tracker | None,
    storage: str | None,
    config: DictConfig,
    direction: str,
) -> None:
    """The best trial -> ``optimization_results.yaml`` in the sweep dir and the parent run."""
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    if not complete:
        log.warning("no trial of study %r completed: no best parameters", study.study_name)
        return
    best, metric = study.best_trial, config.optimized_metric
    results = {
        "name": "optuna",
        "study_name": study.study_name,
        "storage": redacted(storage),
        "optimized_metric": metric,
        "direction": direction,
        "best_trial": best.number,
        "best_value": best.value,
        "best_params": dict(best.params),  # the sampled values; fixed_params were given
        "fixed_params": {k: str(v) for k, v in fixed.items()},
        "trials": {s.name: len(study.get_trials(states=(s,))) for s in DONE},
    }
    path = Path(config.hydra.sweep.dir) / "optimization_results.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(OmegaConf.create(results), path)
    log.info("best trial %d: %s = %s, params %s", best.number, metric, best.value, best.params)
    log.info("written to %s", path)
    if parent is not None:
        log_best(parent, study, best, path)
