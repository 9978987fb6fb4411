"""Sweeps that resume, as a user runs them: a rerun with nothing to do, a resume that finds a new
best trial, a minimized metric, and the refused combinations (one line, nothing created)."""

from __future__ import annotations

import optuna
import pytest
from omegaconf import OmegaConf
from optuna.study import StudyDirection
from optuna.trial import TrialState

from tests.conftest import all_runs, one_line_error, run_cli
from walkers.errors import ConfigError
from walkers.tuning.objective import check_objective
from walkers.tuning.studies import redacted

pytestmark = pytest.mark.slow  # `make test-slow`, beside `make test` in CI

STUDY = "pendulum_tiny"
#: A trial of the pendulum study at its smallest: two evaluations, no pruning (before warm-up).
FAST_TRIAL = [
    "total_steps=400",
    "eval_every=200",
    "checkpoint_every=400",
    "eval_episodes=1",
    "algo.learning_starts=100",
    "torch_threads=1",
]


def storage(store) -> str:
    return f"sqlite:///{store['path'] / 'optuna.db'}"


def run_sweep(store, sweep_dir: str, *args: str):
    """``python -m walkers.train -m sweeps=pendulum_tiny ARGS`` on the test's stores; the
    sweep writes ``optimization_results.yaml`` to ``store/<sweep_dir>``."""
    return run_cli(
        [
            "-m",
            f"sweeps={STUDY}",
            *FAST_TRIAL,
            f"hydra.sweeper.storage={storage(store)}",
            f"hydra.sweep.dir={store['path'] / sweep_dir}",
            *store["overrides"],
            *args,
        ],
        cwd=store["path"],
    )


def ok(result) -> str:
    """The log of a command that must succeed (Hydra's sweeper logs go to stdout)."""
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout + result.stderr


def study_run(store):
    """The study's MLflow parent run (there must be exactly one)."""
    (parent,) = [r for r in all_runs(store["client"]) if r.data.tags.get("walkers.kind") == "study"]
    return parent


def results(store, sweep_dir: str):
    return OmegaConf.load(store["path"] / sweep_dir / "optimization_results.yaml")


def test_a_rerun_reports_and_a_resume_records_a_new_best_trial(store):
    # The episode length is searched: Pendulum pays 0 to 16.3 every step, and an untrained policy
    # cannot hold the pole up, so a 3-step episode (>= -49) scores far above a 60-step one
    # (about -300). Trials 0-2 get 60 and trial 3 gets 3 (enqueued, as a user seeds
    # configurations to try): the best trial of the study changes when it is resumed.
    seeded = optuna.create_study(study_name=STUDY, storage=storage(store), direction="maximize")
    for steps in (60, 60, 60, 3):
        seeded.enqueue_trial({"env.max_episode_steps": steps})
    space = "env.max_episode_steps=choice(60,3)"

    ok(run_sweep(store, "first", space, "hydra.sweeper.n_trials=3"))
    first_best = results(store, "first").best_trial
    assert first_best in (0, 1, 2)
    assert study_run(store).data.tags["best.env.max_episode_steps"] == "60"

    # n_trials below the trials done: nothing to run, the report again, exit 0
    log = ok(run_sweep(store, "rerun", space, "hydra.sweeper.n_trials=2"))
    assert "already has 3 trials (of n_trials=2 asked)" in log
    assert results(store, "rerun").best_trial == first_best
    study = optuna.load_study(study_name=STUDY, storage=storage(store))
    assert len(study.get_trials(states=(TrialState.COMPLETE,))) == 3
    assert study_run(store).info.status == "FINISHED"

    # the same command with n_trials=5: two more trials, and trial 3 (3-step episodes) wins
    ok(run_sweep(store, "resumed", space, "hydra.sweeper.n_trials=5"))
    study = optuna.load_study(study_name=STUDY, storage=storage(store))
    best = study.best_trial
    assert len(study.trials) == 5 and best.number in (3, 4) and best.number != first_best
    assert best.params["env.max_episode_steps"] == 3
    parent = study_run(store)  # still one parent run, now holding the new best
    assert parent.info.status == "FINISHED"
    assert parent.data.tags["best.env.max_episode_steps"] == "3"
    assert float(parent.data.tags["best.algo.lr"]) == pytest.approx(best.params["algo.lr"])
    assert parent.data.metrics["best_trial"] == best.number
    assert parent.data.metrics["best_value"] == pytest.approx(best.value)
    history = store["client"].get_metric_history(parent.info.run_id, "best_value")
    assert [m.step for m in history] == [3, 3, 5]  # trials done at each report
    assert results(store, "resumed").best_trial == best.number


def test_a_minimized_metric_runs_a_minimizing_study(store):
    # a threshold of -1e5 is reached at the first evaluation: steps_to_threshold = 200
    args = ["optimized_metric=final/steps_to_threshold", "env.max_episode_steps=20"]
    ok(run_sweep(store, "min", *args, "env.threshold=-100000", "hydra.sweeper.n_trials=1"))
    study = optuna.load_study(study_name=STUDY, storage=storage(store))
    assert study.direction == StudyDirection.MINIMIZE
    assert study.user_attrs["walkers.optimized_metric"] == "final/steps_to_threshold"
    assert study.best_value == 200.0
    report = results(store, "min")
    assert report.direction == "minimize" and report.best_value == 200.0
    assert study_run(store).data.tags["walkers.direction"] == "minimize"


REFUSED = [
    # (arguments, words the one line must hold)
    (
        ["optimized_metric=final/steps_to_threshold", "hydra.sweeper.direction=maximize"],
        ["hydra.sweeper.direction=maximize", "optimized_metric=final/steps_to_threshold", "min"],
    ),
    (["optimized_metric=loss"], ["optimized_metric='loss'", "final/steps_to_threshold (min"]),
    (["seeds_per_trial=0"], ["seeds_per_trial=0", "an integer >= 1"]),
    # a password on the command line would be written into every job's .hydra/ files
    (
        ["hydra.sweeper.storage='postgresql+psycopg://walker:hunter2@127.0.0.1:1/optuna'"],
        ["carries a password", "walker:***@", "export WALKERS_OPTUNA_STORAGE"],
    ),
    (['hydra.sweeper.study_name="it\'s"'], ['study_name="it\'s"', "no quotes"]),
    (
        ["tracking.uri=http://walker:hunter2@127.0.0.1:1"],
        ["tracking.uri='http://walker:***@127.0.0.1:1'", "MLFLOW_TRACKING_PASSWORD"],
    ),
]


@pytest.mark.parametrize("args,expected", REFUSED, ids=lambda c: " ".join(c))
def test_a_sweep_that_would_optimize_the_wrong_way_is_refused(store, args, expected):
    result = run_sweep(store, "refused", *args)
    error = one_line_error(result)
    assert all(word in error for word in expected), error
    assert "hunter2" not in result.stdout + result.stderr
    assert not (store["path"] / "optuna.db").exists()  # no study
    assert all_runs(store["client"]) == []  # no MLflow run


def test_a_stored_study_is_continued_only_with_its_metric_and_direction(tmp_path):
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    # a maximizing study as a sweep left it before the metric was stored with the study
    study = optuna.create_study(study_name=STUDY, storage=url, direction="maximize")
    with pytest.raises(ConfigError) as error:
        check_objective(study, url, "final/steps_to_threshold")
    assert str(error.value).startswith(
        "optimized_metric=final/steps_to_threshold (minimized) cannot continue study "
        "'pendulum_tiny'"
    )
    check_objective(study, url, "final/auc")  # its direction: continued, and the metric stored
    assert study.user_attrs["walkers.optimized_metric"] == "final/auc"
    with pytest.raises(ConfigError) as error:  # same direction, another metric: not comparable
        check_objective(study, url, "final/return_mean")
    assert "it maximizes final/auc" in str(error.value)


def test_a_trial_left_running_without_a_heartbeat_is_failed_and_retried(store):
    """A sweeper that died right after asking (or a study from before heartbeats) leaves a
    RUNNING trial that never beat: the next sweeper starts its clock, fails it once the grace
    period has passed, retries it, and finishes the study."""
    url = storage(store)
    optuna.create_study(study_name=STUDY, storage=url, direction="maximize").ask()  # orphaned
    ok(
        run_sweep(
            store, "after", "hydra.sweeper.n_trials=2", "optuna.heartbeat_interval=1",
            "optuna.grace_period=2",
        )
    )  # fmt: skip
    trials = optuna.load_study(study_name=STUDY, storage=url).trials
    assert trials[0].state == TrialState.FAIL
    retries = [t for t in trials if t.system_attrs.get("failed_trial") == 0]
    assert len(retries) == 1 and retries[0].state in (TrialState.COMPLETE, TrialState.PRUNED)
    assert len([t for t in trials if t.state != TrialState.FAIL]) == 2  # n_trials done
    assert not [r for r in all_runs(store["client"]) if r.info.status == "RUNNING"]


def test_a_storage_password_never_reaches_logs_or_mlflow():
    url = "postgresql+psycopg://walkers:s3cret@db.example:5432/optuna"
    assert "s3cret" not in redacted(url) and "db.example:5432/optuna" in redacted(url)
    assert redacted("sqlite:////tmp/optuna.db") == "sqlite:////tmp/optuna.db"


def test_the_retry_of_a_pruned_trial_is_told_pruned_without_running(store):
    """A sweeper that died after its trial was pruned but before telling it: the retry the next
    sweeper makes inherits ``pruned_at_step`` and is told PRUNED, not trained again."""
    url = storage(store)
    study = optuna.create_study(study_name=STUDY, storage=url, direction="maximize")
    study.add_trial(optuna.create_trial(state=TrialState.FAIL, user_attrs={"pruned_at_step": 200}))
    study.add_trial(  # what RetryHeartbeatStaleTrialCallback makes of it
        optuna.create_trial(
            state=TrialState.WAITING,
            user_attrs={"pruned_at_step": 200},
            system_attrs={"failed_trial": 0, "retry_history": [0]},
        )
    )
    ok(run_sweep(store, "retry", "hydra.sweeper.n_trials=1"))
    failed, retry = optuna.load_study(study_name=STUDY, storage=url).trials
    assert failed.state == TrialState.FAIL and retry.state == TrialState.PRUNED
    training = [r for r in all_runs(store["client"]) if "walkers.kind" not in r.data.tags]
    assert training == []  # nothing trained again


def test_a_storage_path_with_a_quote_reaches_the_jobs_intact(store):
    """The storage travels to each job as a quoted override: a quote in it must survive."""
    folder = store["path"] / "it's here"
    folder.mkdir()
    url = f"sqlite:///{folder / 'optuna.db'}"
    ok(run_sweep(store, "quoted", "hydra.sweeper.n_trials=1", f'hydra.sweeper.storage="{url}"'))
    (trial,) = optuna.load_study(study_name=STUDY, storage=url).trials
    assert trial.state == TrialState.COMPLETE and trial.intermediate_values  # the job reported
