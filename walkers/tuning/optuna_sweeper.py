"""The Optuna sweeper behind ``python -m walkers.train -m sweeps=NAME`` (the Hydra plugin; what a
study optimizes and how a trial is scored: :mod:`walkers.tuning.objective`; its MLflow runs:
:mod:`walkers.tuning.study_runs`; Optuna internals: :mod:`walkers.tuning.optuna_internals`).

Built on hydra-optuna-sweeper 1.4.0rc3 (its search-space syntax, samplers and trial ->
overrides) with what RL tuning needs and that plugin lacks:

- Direction: the study optimizes ``optimized_metric`` the way :data:`walkers.metrics.
  METRIC_DIRECTIONS` says (``final/steps_to_threshold`` is minimized, returns are maximized).
  Sweep files leave ``hydra.sweeper.direction`` null; one that contradicts the metric, an
  unknown metric, or a stored study of another metric or direction is refused with one
  ``error:`` line and exit 2 before any study or MLflow run is created.
- Pruning: every job gets its trial (``trial.*`` overrides); the trainer reports each evaluation
  to it and stops when the job's pruner says so (:mod:`walkers.tuning.trial`); the trial is
  told PRUNED.
- Resume: ``n_trials`` is the size of the study. Running the same command again continues an
  interrupted study. A rerun with ``n_trials`` at or below the trials already done runs nothing
  and reports the study again.
- Several sweepers, one study (Optuna's distributed optimization; :mod:`walkers.tuning.studies`):
  any number of sweeper processes may run the same command on a shared storage (``optuna=
  postgres``); between them they run exactly ``n_trials`` trials. Each records heartbeats for
  its trials: a trial whose sweeper died is failed after ``optuna.grace_period`` and retried
  (``optuna.max_retry``) by a sweeper still running, or by the next one started. A sweeper
  that is interrupted or whose launcher fails tells its own trials FAIL on the way out.
- Seeds: ``seeds_per_trial=N`` runs every trial on seeds ``seed .. seed+N-1``, N jobs launched
  together; the trial scores the mean of their values and is pruned on the mean of their
  evaluations (:mod:`walkers.tuning.trial`). The trial gets an MLflow run of its own, nested
  under the study's, with its seeds' runs nested under it.
- A job run again (a cluster re-runs a job whose worker died) continues its earlier run:
  each job has a key (study / original trial number / seed) that ``walkers.train`` looks up.
- Divergence: a trial whose score is NaN (or infinitely good) scores the worst finite value so
  far; an infinitely bad score (a threshold never reached) is kept and ranks below all others.
- MLflow: one parent run per study (tag ``walkers.kind=study``), every trial's run (a seed's
  run with ``seeds_per_trial=1``) nested under it and tagged with the study and trial number.
  After every sweep the parent run gets the best trial as values that may change when a
  resumed study finds a better one: tags
  ``best.<param>``, metrics ``best_value`` / ``best_trial`` (step: trials done), and the
  artifact ``optimization_results.yaml`` (also written to the sweep dir).
"""

from __future__ import annotations

import logging
import sys
import time
from contextlib import contextmanager
from typing import Any

import optuna
from hydra.utils import instantiate
from hydra_plugins.hydra_optuna_sweeper._impl import (
    OptunaSweeperImpl,
    create_params_from_overrides,
)
from omegaconf import DictConfig, OmegaConf
from optuna.trial import TrialState

from walkers.errors import ConfigError
from walkers.secrets import redacted
from walkers.tracking.client import Tracker, connect, ending
from walkers.tracking.hydra_callbacks import missing_on_ray_nodes
from walkers.tuning.objective import check_objective, record_outcome, sweep_direction, trials_done
from walkers.tuning.optuna_internals import stored_trial, trial_id
from walkers.tuning.studies import (
    STORAGE_ENV,
    Heartbeats,
    absolute_storage,
    check_passed_by_reference,
    check_study_name,
    counted_trials,
    hydra_quoted,
    job_storage,
    open_storage,
    original_number,
    patiently,
    running,
    study_lock,
    study_uid,
)
from walkers.tuning.study_runs import (
    end_jobs_runs,
    log_trial_outcome,
    open_parent_run,
    open_trial_run,
    report_best,
)
from walkers.tuning.trial import PRUNED_AT

log = logging.getLogger("walkers")

SAMPLER_TARGETS = ("hydra_plugins.hydra_optuna_sweeper.*", "optuna.samplers.*")


class OptunaStudySweeper(OptunaSweeperImpl):
    """Hydra registers it as :class:`walkers.plugins.PruningOptunaSweeper`, which builds it."""

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
            direction,  # as the sweep gave it; sweep() replaces it with the metric's
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
        """Create the study or load it to resume (refused if it was scored by another metric)."""
        metric = self.config.optimized_metric
        settings = self.config.optuna
        study = optuna.create_study(
            study_name=self.study_name,
            storage=self.rdb or None,
            sampler=self.sampler,
            directions=self._get_directions(),
            load_if_exists=True,
        )
        check_objective(study, redacted(self.storage), metric)
        self.uid = f"{study.study_name}-{study_uid(study)}"  # what its jobs' keys start with
        if asked := len(study.trials):
            # A resumed study: a seeded sampler restarted from its seed would propose the same
            # points again, so it continues from seed + the number of trials already asked.
            study.sampler = self.sampler = self._make_sampler(seed_offset=asked)
        if not settings.heartbeat_interval:  # no heartbeats: no other sweeper can be told apart
            for stale in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
                log.warning("trial %d was left running by an interrupted sweep: FAIL", stale.number)
                study.tell(stale.number, state=TrialState.FAIL)
        self._log_size(study, metric)
        return study

    def _check_settings(self) -> None:
        """What the command line may get wrong before any store is touched."""
        self.direction = sweep_direction(self.config.optimized_metric, self.direction)
        if self.study_name is not None:
            check_study_name(self.study_name)
        check_passed_by_reference(self.storage)
        seeds = self.config.seeds_per_trial
        if not isinstance(seeds, int) or isinstance(seeds, bool) or seeds < 1:
            raise ConfigError(f"seeds_per_trial={seeds!r} is not allowed: an integer >= 1")
        if self.storage is None and self.config.hydra.runtime.choices.get("optuna") == "postgres":
            raise ConfigError(
                "optuna=postgres needs its database: export WALKERS_OPTUNA_STORAGE="
                "'postgresql+psycopg://<user>:<password>@<host>/<database>' (`make stack` "
                "prints one) or pass optuna.storage=..."
            )
        self._check_job_environment()

    def _check_job_environment(self) -> None:
        """The nodes that will run the jobs have what the jobs read from their environment (the
        study storage's URL, passed by reference when it holds a password)."""
        reads = [STORAGE_ENV] if f"oc.env:{STORAGE_ENV}" in str(job_storage(self.storage)) else []
        missing = missing_on_ray_nodes(self.config.hydra.launcher, reads)
        if missing:
            node, name = missing[0]
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise ConfigError(
                f"{name} is not set on Ray node {node}{more}: the study's jobs read it there; "
                f"export it on that machine before `ray start` (a Ray worker keeps the "
                "environment its node had at `ray start`)"
            )

    def _claim(self, study: optuna.Study, beats: Heartbeats) -> list[optuna.Trial]:
        """Up to ``n_jobs`` trials for this sweeper while the study (all its sweepers together)
        has started fewer than ``n_trials``: waiting ones first (retries, enqueued trials)."""
        with study_lock(self.rdb, study.study_name) if self.rdb else _unlocked():
            beats.start_clocks(running(study))  # a trial no sweeper ever beat can go stale too
            optuna.storages.fail_stale_trials(study)  # trials of a dead sweeper: FAIL + retry
            trials = study.get_trials(deepcopy=False)
            started = [t for t in counted_trials(trials) if t.state != TrialState.WAITING]
            room = self.n_trials - len(started)
            if len(trials) and self.sampler_cfg.get("seed") is not None:
                # sweepers sharing the study must not draw the same proposals: the sampler's
                # seed moves on with the trials asked so far, whoever asked them
                study.sampler = self.sampler = self._make_sampler(seed_offset=len(trials))
            claimed = [study.ask() for _ in range(max(0, min(self.n_jobs, room)))]
            for trial in claimed:  # beaten before the lock is let go: never without a heartbeat
                beats.add(trial_id(trial))
        return claimed

    def _log_size(self, study: optuna.Study, metric: str) -> None:
        done, name = trials_done(study), study.study_name
        if done >= self.n_trials:
            log.info(
                "study %r in %s already has %d trials (of n_trials=%d asked): nothing to run; "
                "reporting its best (raise hydra.sweeper.n_trials to continue it)",
                name,
                redacted(self.storage),
                done,
                self.n_trials,
            )
        else:
            log.info(
                "study %r in %s: %d of %d trials done; %s %s",
                name,
                redacted(self.storage),
                done,
                self.n_trials,
                self.direction.removesuffix("e") + "ing",
                metric,
            )

    def _job_overrides(
        self, study: optuna.Study, trial: optuna.Trial, parent_id: str | None, key: str, seed: int
    ) -> list[str]:
        overrides = [
            f"trial.study={hydra_quoted(study.study_name)}",
            f"trial.storage={job_storage(self.storage) or 'null'}",  # a secret: by reference
            f"trial.id={trial_id(trial)}",
            f"trial.number={trial.number}",
            f"job_key={hydra_quoted(key)}",
        ]
        if self.config.seeds_per_trial > 1:
            overrides.append(f"seed={seed}")
        if parent_id:
            overrides.append(f"trial.parent_run_id={parent_id}")
        return overrides

    def job_key(self, trial: optuna.trial.FrozenTrial, seed: int) -> str:
        """The key of a trial's job on one seed: the same for every attempt of it (a job Ray
        runs again, a trial a study retries), so that it finds and continues its run."""
        return f"{self.uid}/trial{original_number(trial)}/seed{seed}"

    # --- the loop -----------------------------------------------------------------------------
    def sweep(self, arguments: list[str]) -> None:
        self._process_searchspace_config()
        space, fixed, fixed_overrides = create_params_from_overrides(
            self._parse_sweeper_params_config() + list(arguments)
        )
        for name in fixed:
            space.pop(name, None)
        try:  # both stores answer before anything is created in either
            self._check_settings()
            client = connect(self.config.tracking.uri)
            settings = self.config.optuna
            self.rdb = self.storage and open_storage(
                self.storage, settings.heartbeat_interval, settings.grace_period, settings.max_retry
            )
            study = self._open_study()
        except ConfigError as e:  # raised inside Hydra's multirun: one line, not a traceback
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        with study_lock(self.rdb, study.study_name) if self.rdb else _unlocked():
            parent = open_parent_run(client, self.config, study, self.storage)  # one for all
        settings = self.config.optuna
        poll = min(5, settings.heartbeat_interval or 5)
        self.client = client
        with (
            # one run for all the study's sweepers: the last one out ends it
            ending([parent] if parent is not None else [], lambda: bool(patiently(running, study))),
            Heartbeats(self.rdb, settings.heartbeat_interval if self.rdb else None) as beats,
        ):
            while True:
                if trials := patiently(self._claim, study, beats):
                    if trials := patiently(self._without_decided, study, trials, beats):
                        self._run_batch(study, trials, space, fixed, fixed_overrides, parent, beats)
                elif others := patiently(running, study):  # another sweeper's: wait, retry
                    log.info("waiting for %d trials of other sweepers on the study", len(others))
                    time.sleep(poll)
                else:
                    break
            patiently(report_best, study, fixed, parent, self.storage, self.config, self.direction)

    @staticmethod
    def _without_decided(study, trials, beats) -> list[optuna.Trial]:
        """``trials`` less the retries of trials their pruner had stopped before their sweeper
        died (the retry inherits ``pruned_at_step``): those are told PRUNED, not run again."""
        to_run = []
        for trial in trials:
            if PRUNED_AT in stored_trial(study, trial).user_attrs:
                log.info("trial %d repeats a pruned trial: PRUNED", trial.number)
                study.tell(trial, state=TrialState.PRUNED)
                beats.remove(trial_id(trial))
            else:
                to_run.append(trial)
        return to_run

    def _run_batch(self, study, trials, space, fixed, fixed_overrides, parent, beats) -> None:
        """Launch the jobs of ``trials`` (one per seed), tell the study how each trial ended.

        Raises the first failure when more than ``max_failure_rate`` of the batch failed. On
        the way out for any other reason (Ctrl-C, a launcher that fails) the trials are told
        FAIL and their MLflow runs ended, so nothing is left RUNNING.
        """
        seeds = [self.config.seed + i for i in range(self.config.seeds_per_trial)]
        trial_runs: list[Tracker | None] = []  # per trial (None: one seed, no run)
        opened: list[Tracker] = []
        jobs, keys = [], []  # keys: each job's, to end its runs if the launch fails
        with ending(opened):  # a list that grows: every trial run opened is ended
            try:
                for trial in trials:
                    run = open_trial_run(parent, study, trial) if len(seeds) > 1 else None
                    trial_runs.append(run)
                    opened.extend([run] if run is not None else [])
                params = self._configure_trials(trials, space, fixed, fixed_overrides)
                for trial, job, trial_run in zip(trials, params, trial_runs, strict=True):
                    nest_under = (trial_run or parent) and (trial_run or parent).run_id
                    frozen = stored_trial(study, trial)
                    for seed in seeds:
                        keys.append(self.job_key(frozen, seed))
                        overrides = self._job_overrides(study, trial, nest_under, keys[-1], seed)
                        jobs.append((*job, *overrides))
                returns = self.launcher.launch(jobs, initial_job_idx=self.job_idx)
            except BaseException as e:
                # first the jobs (stopped) and their runs (ended: it never raises), then the trials
                end_jobs_runs(self.client, self.config.tracking.experiment, keys, e)
                for trial in trials:
                    log.warning("trial %d did not finish: FAIL", trial.number)
                    study.tell(trial, state=TrialState.FAIL, skip_if_finished=True)
                    beats.remove(trial_id(trial))
                raise
            self.job_idx += len(returns)
            failures = []
            for i, trial in enumerate(trials):
                results = returns[i * len(seeds) : (i + 1) * len(seeds)]
                failures.append(patiently(record_outcome, study, trial, results))
                beats.remove(trial_id(trial))
            for trial, trial_run in zip(trials, trial_runs, strict=True):  # all told first
                if trial_run is not None:
                    try:
                        log_trial_outcome(trial_run, study, trial, self.config.optimized_metric)
                    except Exception as e:  # the study has the outcome; MLflow's copy is extra
                        log.warning("trial %d's outcome not logged to MLflow: %s", trial.number, e)
        failures = [e for e in failures if e is not None]
        if len(failures) / len(trials) > self.max_failure_rate:
            raise failures[0]


@contextmanager
def _unlocked():
    yield
