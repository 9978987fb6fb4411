"""Optuna sweeps through Hydra --multirun: a real tiny study, resume, pruning, divergence."""

from __future__ import annotations

import math

import optuna
import pytest
from hydra.core.utils import JobReturn, JobStatus
from hydra_plugins.hydra_optuna_sweeper.config import Direction
from omegaconf import OmegaConf
from optuna.trial import TrialState

from tests.conftest import all_runs, one_line_error, run_cli
from walkers.errors import ConfigError
from walkers.tuning.objective import record_outcome, sweep_direction
from walkers.tuning.trial import TrialReporter

#: A trial of the pendulum study at test size.
TINY_TRIAL = [
    "total_steps=600",
    "eval_every=200",
    "checkpoint_every=600",
    "eval_episodes=1",
    "algo.learning_starts=100",
]


def sweep(store, *args):
    storage = f"sqlite:///{store['path'] / 'optuna.db'}"
    result = run_cli(
        [
            "-m",
            "sweeps=pendulum_tiny",
            *TINY_TRIAL,
            f"hydra.sweeper.storage={storage}",
            *store["overrides"],
            *args,
        ],
        cwd=store["path"],
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return optuna.load_study(study_name="pendulum_tiny", storage=storage)


@pytest.mark.slow  # `make test-slow`
def test_study_runs_resumes_and_logs_every_trial(store):
    study = sweep(store, "hydra.sweeper.n_trials=3")
    assert len(study.trials) == 3
    assert all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in study.trials)
    (results_file,) = store["path"].glob("multirun/*/*/optimization_results.yaml")
    results = OmegaConf.load(results_file)
    assert results.best_trial == study.best_trial.number
    assert dict(results.best_params) == study.best_trial.params

    runs = all_runs(store["client"])
    (parent,) = [r for r in runs if r.data.tags.get("walkers.kind") == "study"]
    trial_runs = [r for r in runs if r.data.tags.get("walkers.study") == "pendulum_tiny"]
    trial_runs = [r for r in trial_runs if r.info.run_id != parent.info.run_id]
    assert sorted(int(r.data.tags["walkers.trial"]) for r in trial_runs) == [0, 1, 2]
    assert {r.data.tags["mlflow.parentRunId"] for r in trial_runs} == {parent.info.run_id}
    for run in trial_runs:  # each trial's sampled values are its run's params
        trial = study.trials[int(run.data.tags["walkers.trial"])]
        assert float(run.data.params["algo.lr"]) == pytest.approx(trial.params["algo.lr"])
    assert parent.data.metrics["best_value"] == pytest.approx(study.best_value)

    # the same command with a larger n_trials continues the study (and its MLflow parent run)
    resumed = sweep(store, "hydra.sweeper.n_trials=4")
    assert len(resumed.trials) == 4
    new = resumed.trials[3].params
    assert all(new != t.params for t in resumed.trials[:3])  # the sampler did not restart
    parents = [r for r in all_runs(store["client"]) if r.data.tags.get("walkers.kind") == "study"]
    assert [p.info.run_id for p in parents] == [parent.info.run_id]


def test_a_hopeless_trial_is_pruned_early(store):
    # Pendulum returns are always negative: a threshold pruner at 0 stops at the first eval,
    # and nothing due after the evaluation at that step runs (the video of step 200)
    study = sweep(
        store,
        "hydra.sweeper.n_trials=1",
        "sweep/pruner=threshold",
        "sweep.pruner.lower=0.0",
        "sweep.warmup_steps=0",
        "video_every=100",
    )
    (trial,) = study.trials
    assert trial.state == TrialState.PRUNED and trial.user_attrs["pruned_at_step"] == 200
    (run,) = [r for r in all_runs(store["client"]) if r.data.tags.get("walkers.trial") == "0"]
    assert run.data.tags["walkers.pruned_at_step"] == "200"
    steps = [
        m.step for m in store["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    ]
    assert steps == [200]  # it stopped there instead of training to 600
    videos = [a.path for a in store["client"].list_artifacts(run.info.run_id, "videos")]
    assert len(videos) == 1 and "100" in videos[0], videos  # step 100's, not 200's


def _job_return(value=None, error: Exception | None = None) -> JobReturn:
    ret = JobReturn()
    ret.status = JobStatus.FAILED if error else JobStatus.COMPLETED
    ret._return_value = error if error else value
    return ret


def test_diverged_trial_scores_the_worst_finite_value_and_errors_fail():
    study = optuna.create_study(direction="maximize")
    for value in (-100.0, -500.0):
        study.tell(study.ask(), value)
    diverged = study.ask()
    # a trial's jobs: one per seed; a seed that diverged makes the trial's mean NaN
    assert record_outcome(study, diverged, [_job_return(-50.0), _job_return(math.nan)]) is None
    assert study.trials[2].value == -500.0 and study.trials[2].user_attrs["diverged"]
    crashed = study.ask()
    error = record_outcome(study, crashed, [_job_return(error=RuntimeError("boom"))])
    assert isinstance(error, RuntimeError) and study.trials[3].state == TrialState.FAIL
    two_seeds = study.ask()
    assert record_outcome(study, two_seeds, [_job_return(-100.0), _job_return(-200.0)]) is None
    assert study.trials[4].value == -150.0  # the mean over the seeds


def test_a_minimizing_study_ranks_a_never_reached_threshold_worst():
    # final/steps_to_threshold is inf for a trial that never reached the threshold
    study = optuna.create_study(direction="minimize")
    study.tell(study.ask(), 3000.0)
    assert record_outcome(study, study.ask(), [_job_return(math.inf)]) is None
    assert study.trials[1].value == math.inf and "diverged" not in study.trials[1].user_attrs
    assert record_outcome(study, study.ask(), [_job_return(math.nan)]) is None  # diverged
    assert study.trials[2].value == 3000.0 and study.trials[2].user_attrs["diverged"]
    assert study.best_trial.number == 0
    study.tell(study.ask(), 2000.0)
    assert study.best_trial.number == 3


PRUNERS = {
    "median": {"_target_": "optuna.pruners.MedianPruner", "n_startup_trials": 1},
    "threshold": {"_target_": "optuna.pruners.ThresholdPruner", "lower": -1000.0},
}


@pytest.mark.parametrize("direction", ["maximize", "minimize"])
@pytest.mark.parametrize("pruner", PRUNERS)
def test_pruners_stop_low_eval_returns_whichever_way_the_study_goes(tmp_path, pruner, direction):
    # a trial reports eval returns (higher is better) also to a study that minimizes its metric
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    study = optuna.create_study(study_name="s", storage=storage, direction=direction)

    def reporter() -> TrialReporter:
        job = {"study": "s", "storage": storage, "id": study.ask()._trial_id}
        return TrialReporter(OmegaConf.create(job), OmegaConf.create(PRUNERS[pruner]))

    first = reporter()
    assert not first(200, -500.0)
    study.tell(first.trial.number, 0.0)  # complete: the median pruner compares with it
    assert reporter()(200, -1500.0)  # a lower eval return: pruned
    assert not reporter()(200, -100.0)  # a higher one runs on


def test_sweep_direction_follows_the_metric():
    assert sweep_direction("final/auc", None) == "maximize"
    assert sweep_direction("final/steps_to_threshold", None) == "minimize"
    assert sweep_direction("final/steps_to_threshold", Direction.minimize) == "minimize"
    assert sweep_direction("final/return_mean", ["maximize"]) == "maximize"
    for metric, direction in (("final/auc", "minimize"), ("final/auc", "up")):
        with pytest.raises(ConfigError, match="hydra.sweeper.direction="):
            sweep_direction(metric, direction)


@pytest.mark.slow  # `make test-slow`: a whole sweep, then a run of its preset
def test_best_trial_becomes_a_preset(store):
    study = sweep(store, "hydra.sweeper.n_trials=2")
    storage = f"sqlite:///{store['path'] / 'optuna.db'}"
    args = ["study=pendulum_tiny", f"storage={storage}", "name=tiny_tuned", f"dir={store['path']}"]
    result = run_cli(args, cwd=store["path"], module="walkers.preset")
    assert result.returncode == 0, result.stderr[-2000:]
    preset = OmegaConf.load(store["path"] / "tiny_tuned.yaml")
    assert preset.algo.lr == pytest.approx(study.best_trial.params["algo.lr"])
    assert "override /algo: td3" in (store["path"] / "tiny_tuned.yaml").read_text()
    again = run_cli(args, cwd=store["path"], module="walkers.preset")  # never overwritten silently
    assert "force=true" in one_line_error(again)
    missing = run_cli(["study=nope"], cwd=store["path"], module="walkers.preset")
    assert "study='nope' is not a file in sweeps/" in one_line_error(missing)
