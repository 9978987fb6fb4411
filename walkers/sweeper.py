"""The Optuna sweeper behind ``python -m walkers.train -m sweeps=NAME``.

Built on hydra-optuna-sweeper 1.4.0rc3 (its search-space syntax, samplers and trial ->
overrides) with what RL tuning needs and that plugin lacks:

- Pruning: every job gets its trial (``sweep.*`` overrides); the trainer reports each evaluation
  to it and stops when the job's pruner says so (:mod:`walkers.trial`); the trial is told PRUNED.
- Resume: ``n_trials`` is the size of the study. Running the same command again continues an
  interrupted study; trials an interrupted sweep left RUNNING are marked FAIL.
- Divergence: a trial whose score is NaN/inf scores the worst finite value so far.
- MLflow: one parent run per study (tag ``walkers.kind=study``), every trial's run nested under
  it and tagged with the study and trial number; the best trial is logged to the parent, and
  ``optimization_results.yaml`` is written to the sweep dir and logged.
"""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path
from typing import Any

import optuna
from hydra.core.utils import JobReturn
from hydra.utils import instantiate
from hydra_plugins.hydra_optuna_sweeper._impl import (
    OptunaSweeperImpl,
    create_params_from_overrides,
)
from omegaconf import DictConfig, OmegaConf
from optuna.trial import TrialState

from walkers import tracking
from walkers.trial import PRUNED_AT

log = logging.getLogger("walkers")

SAMPLER_TARGETS = ("hydra_plugins.hydra_optuna_sweeper.*", "optuna.samplers.*")
DONE = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
STUDY_TAG = "walkers.study"


def absolute_storage(storage: str | None) -> str | None:
    """``sqlite:///rel.db`` -> an absolute path, so every job finds the same file."""
    if storage and storage.startswith("sqlite:///") and not storage.startswith("sqlite:////"):
        return f"sqlite:///{Path(storage.removeprefix('sqlite:///')).resolve()}"
    return storage


def worst_finite(study: optuna.Study) -> float:
    """The worst score among completed trials (the floor of the range if there is none)."""
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    values = [t.value for t in complete if t.value is not None and math.isfinite(t.value)]
    maximize = study.direction == optuna.study.StudyDirection.MAXIMIZE
    if not values:
        return -sys.float_info.max if maximize else sys.float_info.max
    return min(values) if maximize else max(values)


def record_outcome(study: optuna.Study, trial: optuna.Trial, result: JobReturn) -> Exception | None:
    """Tell the study how a trial's job ended; returns the job's exception if it failed.

    Pruned (the job set ``pruned_at_step``) -> PRUNED; a NaN/inf score -> the worst finite
    score so far (a diverged configuration is bad, not an error); an exception -> FAIL.
    """
    try:
        value = float(result.return_value)  # re-raises what the job raised
    except Exception as e:
        study.tell(trial, state=TrialState.FAIL)
        log.warning("trial %d failed: %s", trial.number, e)
        return e
    (frozen,) = [t for t in study.get_trials(deepcopy=False) if t.number == trial.number]
    if PRUNED_AT in frozen.user_attrs:
        study.tell(trial, state=TrialState.PRUNED)
    elif not math.isfinite(value):
        worst = worst_finite(study)
        log.warning(
            "trial %d diverged (%s): scored %s, the worst so far", trial.number, value, worst
        )
        trial.set_user_attr("diverged", True)
        study.tell(trial, worst)
    else:
        study.tell(trial, value)
    return None


class PruningOptunaSweeper(OptunaSweeperImpl):
    def __init__(
        self,
        sampler: Any,
        direction: Any,
        storage: str | None,
        study_name: str | None,
        n_trials: int,
        n_jobs: int,
        max_failure_rate: float,
        custom_search_space: str | None,
        params: DictConfig | None,
    ) -> None:
        self.sampler_cfg = sampler
        super().__init__(
            self._make_sampler(),
            direction,
            absolute_storage(storage),
            study_name,
            n_trials,
            n_jobs,
            max_failure_rate,
            custom_search_space,
            params,
        )

    def _make_sampler(self, seed_offset: int = 0):
        cfg = self.sampler_cfg
        if seed_offset and cfg.get("seed") is not None:
            cfg = OmegaConf.merge(cfg, {"seed": cfg.seed + seed_offset})
        return instantiate(cfg, _execution_whitelist_=SAMPLER_TARGETS)

    # --- the study ----------------------------------------------------------------------------
    def _open_study(self) -> optuna.Study:
        study = optuna.create_study(
            study_name=self.study_name,
            storage=self.storage,
            sampler=self.sampler,
            directions=self._get_directions(),
            load_if_exists=True,
        )
        if asked := len(study.trials):
            # A resumed study: a seeded sampler restarted from its seed would propose the same
            # points again, so it continues from seed + the number of trials already asked.
            study.sampler = self.sampler = self._make_sampler(seed_offset=asked)
        for stale in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            log.warning("trial %d was left running by an interrupted sweep: FAIL", stale.number)
            study.tell(stale.number, state=TrialState.FAIL)
        done = len(study.get_trials(deepcopy=False, states=DONE))
        log.info(
            "study %r in %s: %d of %d trials done",
            study.study_name,
            self.storage,
            done,
            self.n_trials,
        )
        return study

    def _job_overrides(self, study: optuna.Study, trial: optuna.Trial, parent_id: str | None):
        overrides = [
            f"sweep.study='{study.study_name}'",
            f"sweep.storage='{self.storage}'",
            f"sweep.trial_id={trial._trial_id}",
            f"sweep.trial_number={trial.number}",
        ]
        if parent_id:
            overrides.append(f"sweep.parent_run_id={parent_id}")
        return overrides

    # --- the loop -----------------------------------------------------------------------------
    def sweep(self, arguments: list[str]) -> None:
        self._process_searchspace_config()
        space, fixed, fixed_overrides = create_params_from_overrides(
            self._parse_sweeper_params_config() + list(arguments)
        )
        for name in fixed:
            space.pop(name, None)
        study = self._open_study()
        parent = open_parent_run(self.config, study, self.storage)
        status = tracking.FAILED
        try:
            while todo := self.n_trials - len(study.get_trials(deepcopy=False, states=DONE)):
                trials = [study.ask() for _ in range(min(todo, self.n_jobs))]
                overrides = [
                    (*job, *self._job_overrides(study, trial, parent and parent.run_id))
                    for job, trial in zip(
                        self._configure_trials(trials, space, fixed, fixed_overrides),
                        trials,
                        strict=True,
                    )
                ]
                returns = self.launcher.launch(overrides, initial_job_idx=self.job_idx)
                self.job_idx += len(returns)
                failures = [
                    record_outcome(study, t, r) for t, r in zip(trials, returns, strict=True)
                ]
                failures = [e for e in failures if e is not None]
                if len(failures) / len(returns) > self.max_failure_rate:
                    raise failures[0]
            self._report(study, fixed, parent)
            status = tracking.FINISHED
        except KeyboardInterrupt:
            status = tracking.KILLED
            raise
        finally:
            if parent is not None:
                parent.end(status)

    def _report(self, study: optuna.Study, fixed: dict, parent: tracking.Tracker | None) -> None:
        """Best trial -> ``optimization_results.yaml`` in the sweep dir and the parent run."""
        complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        if not complete:
            log.warning("no trial of study %r completed: no best parameters", study.study_name)
            return
        best = study.best_trial
        results = {
            "name": "optuna",
            "study_name": study.study_name,
            "storage": self.storage,
            "best_trial": best.number,
            "best_value": best.value,
            "best_params": dict(best.params),  # the sampled values; fixed_params were given
            "fixed_params": {k: str(v) for k, v in fixed.items()},
            "trials": {s.name: len(study.get_trials(states=(s,))) for s in DONE},
        }
        path = Path(self.config.hydra.sweep.dir) / "optimization_results.yaml"
        path.parent.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(OmegaConf.create(results), path)
        log.info("best trial %d: %s = %s, params %s", best.number, "value", best.value, best.params)
        log.info("written to %s", path)
        if parent is not None:
            parent.log_params({f"best.{k}": v for k, v in best.params.items()})
            parent.log_metrics({"best_value": best.value, "best_trial": best.number}, step=0)
            parent.log_artifact(path)
            log.info("MLflow parent run: `make ui`, then %s", parent.url)


def open_parent_run(
    config: DictConfig, study: optuna.Study, storage: str | None
) -> tracking.Tracker | None:
    """The study's MLflow parent run: reopened when a study is resumed, else created."""
    try:
        client = tracking.connect(config.tracking.uri)
    except Exception as e:  # the jobs will report a bad store as a one-line error
        log.warning("no MLflow parent run for the study: %s", e)
        return None
    experiment_id = tracking.get_or_create_experiment(client, config.tracking.experiment)
    spool = Path(config.work_dir) / "spool"
    query = f"tags.`walkers.kind` = 'study' and tags.`{STUDY_TAG}` = '{study.study_name}'"
    for run in tracking.search_runs(client, experiment_id, query):
        return tracking.Tracker.reopen(client, run.info.run_id, spool)
    return tracking.Tracker.start(
        client,
        config.tracking.experiment,
        run_name=f"study-{study.study_name}",
        tags={
            tracking.KIND_TAG: "study",
            STUDY_TAG: study.study_name,
            "optuna.storage": str(storage),
        },
        spool_dir=spool,
    )
