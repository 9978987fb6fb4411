"""Scale-out with the real parts: a Ray cluster on loopback (a head and a worker node), PostgreSQL
(pgserver) behind Optuna and an MLflow tracking server, all started here (`make test-cluster`).

The same commands as on one machine, with ``hydra/launcher=ray_cluster tracking=server
optuna=postgres``: sweeps with several seeds per trial across the nodes, two sweepers on one
study, a job's worker killed mid-trial, a sweeper killed mid-trial, runs evaluated, collected
and resumed from another directory, the submitit launcher, and bad addresses refused.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import optuna
import pytest
from mlflow.tracking import MlflowClient
from optuna.trial import TrialState

from tests import cluster_kit
from tests.cluster_kit import LONGER_TRIAL, TRIAL, LocalRay, free_port, runs_of, start_stack
from tests.conftest import one_line_error, run_cli, spawn_cli
from walkers.tracking.servers import start_mlflow_server
from walkers.tuning.studies import STORAGE_ENV

pytestmark = pytest.mark.cluster


@pytest.fixture(scope="module")
def stack():
    """PostgreSQL with the mlflow and optuna databases (the latter takes a password, which every
    command here gets by reference: WALKERS_OPTUNA_STORAGE), an MLflow server on it."""
    # Not under pytest's tmp root: PostgreSQL runs as the unprivileged user `pgserver`, and any
    # other pytest session that starts on the machine resets that root to mode 0700, which cuts
    # PostgreSQL off from its own data ("PANIC: could not open file .../pg_control: Permission
    # denied"), then the MLflow server (503) and every study with it.
    folder = Path(tempfile.mkdtemp(prefix="walkers-stack-"))
    kit = start_stack(folder)
    before = os.environ.get(STORAGE_ENV)
    os.environ[STORAGE_ENV] = kit.optuna_url  # every command started here inherits it
    yield {
        "tracking": kit.tracking,
        "optuna": kit.admin_optuna_url,
        "client": MlflowClient(kit.tracking),
        "backend": kit.backend,
        "folder": kit.folder,
        "kit": kit,
    }
    if before is None:
        os.environ.pop(STORAGE_ENV, None)
    else:
        os.environ[STORAGE_ENV] = before
    kit.stop()
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def ray_cluster(stack):
    """A head and a worker node on loopback, one CPU each (so jobs spread over both); the nodes
    have the study's storage in their environment, as a cluster's machines would."""
    ray = LocalRay(nodes=2, env={STORAGE_ENV: stack["kit"].optuna_url}).start()
    yield ray
    ray.stop()


def stores(stack, experiment: str) -> list[str]:
    return cluster_kit.stores(stack["kit"], experiment)


def on_ray(ray: LocalRay) -> list[str]:
    return ["hydra/launcher=ray_cluster", f"hydra.launcher.ray.init.address={ray.address}"]


def study(stack, name: str) -> optuna.Study:
    return optuna.load_study(study_name=name, storage=stack["optuna"])


def ok(result) -> str:
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]
    return result.stdout + result.stderr


def assert_nothing_running(stack, experiment: str, study_name: str) -> None:
    assert not study(stack, study_name).get_trials(states=(TrialState.RUNNING,))
    statuses = Counter(r.info.status for r in runs_of(stack["client"], experiment))
    assert set(statuses) == {"FINISHED"}, statuses


def test_a_sweep_with_two_seeds_per_trial_runs_across_the_cluster(stack, ray_cluster, tmp_path):
    name = "cluster_seeds"
    output = ok(
        run_cli(
            [
                "-m", "sweeps=pendulum_tiny", *TRIAL, *stores(stack, name), *on_ray(ray_cluster),
                f"hydra.sweeper.study_name={name}", "hydra.sweeper.n_trials=4",
                "hydra.sweeper.n_jobs=2", "seeds_per_trial=2", f"hydra.sweep.dir={tmp_path}/sweep",
            ],
            cwd=tmp_path,
            timeout=900,
        )
    )  # fmt: skip
    trials = study(stack, name).trials
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 4

    runs = runs_of(stack["client"], name)
    kinds = Counter(r.data.tags.get("walkers.kind", "train") for r in runs)
    assert kinds == {"study": 1, "trial": 4, "train": 8}
    (parent,) = [r for r in runs if r.data.tags.get("walkers.kind") == "study"]
    trial_runs = {r.info.run_id: r for r in runs if r.data.tags.get("walkers.kind") == "trial"}
    assert {r.data.tags["mlflow.parentRunId"] for r in trial_runs.values()} == {parent.info.run_id}
    seed_runs = [r for r in runs if "walkers.kind" not in r.data.tags]
    for run in seed_runs:  # every seed nested under its trial, its checkpoints on the server
        trial_run = trial_runs[run.data.tags["mlflow.parentRunId"]]
        assert run.data.tags["walkers.trial"] == trial_run.data.tags["walkers.trial"]
        artifacts = [a.path for a in stack["client"].list_artifacts(run.info.run_id, "checkpoints")]
        assert "checkpoints/last.pt" in artifacts
    for trial in trials:  # the trial's value is the mean over its two seeds
        seeds = [r for r in seed_runs if r.data.tags["walkers.trial"] == str(trial.number)]
        assert sorted(r.data.tags["seed"] for r in seeds) == ["0", "1"]
        mean = sum(r.data.metrics["final/auc"] for r in seeds) / 2
        assert trial.value == pytest.approx(mean)
    assert len({r.data.tags["walkers.worker"] for r in seed_runs}) == 2  # both Ray nodes trained
    assert_nothing_running(stack, name, name)

    # The study's password went to the jobs by reference only: their overrides say where it is,
    # and it is in no file (sweep dir, job dirs, local run folders, Ray's session logs, the
    # server's artifacts and log), no console line, no MLflow param or tag.
    kit = stack["kit"]
    overrides = (tmp_path / "sweep" / "0" / ".hydra" / "overrides.yaml").read_text()
    assert f"trial.storage='${{oc.env:{STORAGE_ENV}}}'" in overrides
    broken = cluster_kit.broken_promises(
        kit, name, [tmp_path, *ray_cluster.places(), *kit.places()], [output], compare=False
    )
    assert broken == []
    assert ray_cluster.places() and any(ray_cluster.temp_dir.rglob("runtime_env_agent.log"))


def test_two_sweepers_on_one_study_run_exactly_n_trials(stack, tmp_path):
    name = "cluster_two_sweepers"
    command = [
        sys.executable, "-m", "walkers.train", "-m", "sweeps=pendulum_tiny", *TRIAL,
        *stores(stack, name), f"hydra.sweeper.study_name={name}", "hydra.sweeper.n_trials=5",
    ]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    sweepers = [
        subprocess.Popen(
            [*command, f"hydra.sweep.dir={tmp_path}/sweeper{i}"],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    logs = [p.communicate(timeout=900)[0] for p in sweepers]
    for process, log in zip(sweepers, logs, strict=True):
        assert process.returncode == 0, log[-3000:]
    trials = study(stack, name).trials
    assert len(trials) == 5
    assert all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
    runs = runs_of(stack["client"], name)
    assert Counter(r.data.tags.get("walkers.kind", "train") for r in runs) == {
        "study": 1,
        "train": 5,
    }
    assert_nothing_running(stack, name, name)


def _running_run_with_checkpoint(client, experiment: str, process: subprocess.Popen):
    """Wait until a training run of ``experiment`` is RUNNING with checkpoints/last.pt uploaded."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()[0][-3000:]
        if client.get_experiment_by_name(experiment) is not None:
            for run in runs_of(client, experiment):
                if run.info.status == "RUNNING" and "walkers.kind" not in run.data.tags:
                    paths = [a.path for a in client.list_artifacts(run.info.run_id, "checkpoints")]
                    if "checkpoints/last.pt" in paths:
                        return run
        time.sleep(0.5)
    raise AssertionError("no run uploaded a checkpoint in time")


def test_a_job_whose_worker_is_killed_continues_its_run_on_a_retry(stack, ray_cluster, tmp_path):
    name = "cluster_worker_killed"
    sweeper = spawn_cli(
        [
            "-m", "sweeps=pendulum_tiny", *LONGER_TRIAL, *stores(stack, name),
            *on_ray(ray_cluster), f"hydra.sweeper.study_name={name}", "hydra.sweeper.n_trials=2",
            "pruner=none", f"hydra.sweep.dir={tmp_path}/sweep",
        ],
        tmp_path,
        merge_output=True,
    )  # fmt: skip
    try:
        victim = _running_run_with_checkpoint(stack["client"], name, sweeper)
        jobs = ray_cluster.jobs()
        assert len(jobs) == 1, jobs  # n_jobs=1: the one job training now
        jobs[0].send_signal(signal.SIGKILL)
        log = sweeper.communicate(timeout=900)[0]
    finally:
        if sweeper.poll() is None:
            sweeper.kill()
    assert sweeper.returncode == 0, log[-3000:]
    assert "continuing it from its last checkpoint" in log
    assert [t.state for t in study(stack, name).trials] == [TrialState.COMPLETE] * 2
    runs = [r for r in runs_of(stack["client"], name) if "walkers.kind" not in r.data.tags]
    assert len(runs) == 2  # the killed job's run was continued, not duplicated
    continued = stack["client"].get_run(victim.info.run_id)
    assert continued.info.status == "FINISHED" and continued.data.metrics["final/auc"]
    history = stack["client"].get_metric_history(victim.info.run_id, "eval/return_mean")
    steps = [m.step for m in history]
    assert len(steps) == len(set(steps)) and max(steps) == 3000
    assert_nothing_running(stack, name, name)


def test_a_killed_sweeper_s_trial_is_failed_retried_and_its_run_continued(stack, tmp_path):
    name = "cluster_sweeper_killed"
    command = [
        "-m", "sweeps=pendulum_tiny", *LONGER_TRIAL, *stores(stack, name), "pruner=none",
        f"hydra.sweeper.study_name={name}", "hydra.sweeper.n_trials=2", "seeds_per_trial=2",
        "optuna.heartbeat_interval=1", "optuna.grace_period=4",
    ]  # fmt: skip
    first = spawn_cli([*command, f"hydra.sweep.dir={tmp_path}/first"], tmp_path, merge_output=True)
    try:
        victim = _running_run_with_checkpoint(stack["client"], name, first)
        first.send_signal(signal.SIGKILL)  # the sweeper and its in-process job die together
        first.communicate(timeout=60)
    finally:
        if first.poll() is None:
            first.kill()
    assert study(stack, name).trials[0].state == TrialState.RUNNING  # left behind, beating no more

    log = ok(run_cli([*command, f"hydra.sweep.dir={tmp_path}/second"], cwd=tmp_path, timeout=900))
    assert "continuing it from its last checkpoint" in log
    trials = study(stack, name).trials
    retried = [t for t in trials if t.system_attrs.get("failed_trial") == 0]
    assert trials[0].state == TrialState.FAIL and len(retried) == 1
    assert retried[0].state == TrialState.COMPLETE
    assert len([t for t in trials if t.state == TrialState.COMPLETE]) == 2  # n_trials done
    continued = stack["client"].get_run(victim.info.run_id)
    assert continued.info.status == "FINISHED"
    assert continued.data.tags["walkers.trial"] == str(retried[0].number)
    runs = runs_of(stack["client"], name)
    trial_runs = [r for r in runs if r.data.tags.get("walkers.kind") == "trial"]
    assert len(trial_runs) == 2  # the retry took over the dead trial's run
    assert len([r for r in runs if "walkers.kind" not in r.data.tags]) == 4  # 2 trials x 2 seeds
    assert_nothing_running(stack, name, name)  # trial runs included


def test_runs_on_the_server_are_evaluated_collected_compared_and_resumed_elsewhere(
    stack, ray_cluster, tmp_path
):
    name = "cluster_seed_study"
    trained, elsewhere = tmp_path / "trained", tmp_path / "elsewhere"
    trained.mkdir()
    elsewhere.mkdir()
    ok(
        run_cli(
            [
                "-m", "algo=td3,ddpg", "seed=0,1", "env=pendulum", *TRIAL, *stores(stack, name),
                *on_ray(ray_cluster), f"work_dir={trained / '.walkers'}",
                f"hydra.sweep.dir={trained}/multirun",
            ],
            cwd=trained,
            timeout=900,
        )
    )  # fmt: skip
    runs = runs_of(stack["client"], name)
    assert len(runs) == 4 and all(r.info.status == "FINISHED" for r in runs)
    server = [f"tracking.uri={stack['tracking']}", f"tracking.experiment={name}"]

    report = ok(
        run_cli(
            ["env=pendulum", "algos=[ddpg,td3]", *server, f"out={elsewhere / 'report'}"],
            cwd=elsewhere,
            module="walkers.compare",
        )
    )
    assert (elsewhere / "report" / "report.md").is_file(), report[-2000:]

    td3 = next(r for r in runs if r.data.tags["algo"] == "td3")
    run_id = td3.info.run_id
    evaluate = [f"run_id={run_id}", "episodes=2", "video=false", *server]
    ok(run_cli(evaluate, cwd=elsewhere, module="walkers.evaluate"))
    datasets = tmp_path / "datasets"
    ok(
        run_cli(
            [f"run_id={run_id}", "episodes=2", "dataset=cluster/pendulum/td3-v0", *server],
            cwd=elsewhere,
            module="walkers.collect",
            env_overrides={"MINARI_DATASETS_PATH": str(datasets)},
        )
    )
    assert (datasets / "cluster" / "pendulum" / "td3-v0").is_dir()

    # No local copy here: the checkpoint comes from the server (its buffer refilled, as said).
    resumed = ok(run_cli([f"resume={run_id}", "total_steps=900", *server], cwd=elsewhere))
    assert "refilling" in resumed
    run = stack["client"].get_run(run_id)
    assert run.info.status == "FINISHED" and "buffer_refill" in " ".join(run.data.tags)
    steps = [m.step for m in stack["client"].get_metric_history(run_id, "eval/return_mean")]
    assert steps == [300, 600, 900]


def test_the_submitit_launcher_runs_jobs_too(stack, tmp_path):
    name = "cluster_submitit"
    ok(
        run_cli(
            [
                "-m", "hydra/launcher=submitit_local", "algo=td3", "env=pendulum", "seed=0,1",
                *TRIAL, *stores(stack, name), f"hydra.sweep.dir={tmp_path}/multirun",
            ],
            cwd=tmp_path,
            timeout=600,
        )
    )  # fmt: skip
    runs = runs_of(stack["client"], name)
    assert sorted(r.data.tags["seed"] for r in runs) == ["0", "1"]
    assert all(r.info.status == "FINISHED" for r in runs)


@pytest.mark.parametrize(
    "bad, names",
    [
        (["optuna.storage='postgresql+psycopg://nobody@/optuna?host=/nonexistent'"],
         "hydra.sweeper.storage="),
        (["hydra/launcher=ray_cluster", "hydra.launcher.ray.init.address=127.0.0.1:1"],
         "hydra.launcher.ray.init.address='127.0.0.1:1'"),
        (["tracking.uri=http://127.0.0.1:1"], "tracking.uri='http://127.0.0.1:1'"),
    ],
)  # fmt: skip
def test_bad_addresses_are_one_line_errors_and_create_nothing(stack, tmp_path, bad, names):
    name = "cluster_bad_input"
    result = run_cli(
        ["-m", "sweeps=pendulum_tiny", *TRIAL, *stores(stack, name),
         f"hydra.sweeper.study_name={name}", f"hydra.sweep.dir={tmp_path}/sweep", *bad],
        cwd=tmp_path,
        timeout=300,
    )  # fmt: skip
    line = one_line_error(result)
    assert names in line
    assert stack["client"].get_experiment_by_name(name) is None  # no MLflow experiment or run
    assert name not in optuna.get_all_study_names(storage=stack["optuna"])  # no study


def test_training_goes_on_while_the_tracking_server_restarts(stack, tmp_path):
    """The server stops mid-run and comes back: the run finishes and every metric arrives."""
    port = free_port()
    server = start_mlflow_server(stack["backend"], stack["folder"] / "artifacts", port, workers=1)
    client = MlflowClient(server.url)
    name = "cluster_server_restart"
    args = [
        "algo=td3", "env=pendulum", *TRIAL, "total_steps=8000", "eval_every=400",
        "checkpoint_every=4000", "tracking=server", f"tracking.uri={server.url}",
        f"tracking.experiment={name}", f"work_dir={tmp_path / '.walkers'}",
    ]  # fmt: skip
    training = spawn_cli(args, tmp_path, merge_output=True)
    try:
        deadline = time.monotonic() + 300
        while not (
            client.get_experiment_by_name(name)
            and [m for r in runs_of(client, name)
                 for m in client.get_metric_history(r.info.run_id, "eval/return_mean")]
        ):  # fmt: skip
            assert training.poll() is None and time.monotonic() < deadline
            time.sleep(0.5)
        server.stop()  # down while the run keeps training
        time.sleep(8)
        assert training.poll() is None  # training did not stop
        server = start_mlflow_server(
            stack["backend"], stack["folder"] / "artifacts", port, workers=1
        )
        log = training.communicate(timeout=600)[0]
    finally:
        if training.poll() is None:
            training.kill()
        server.stop()
    assert training.returncode == 0, log[-3000:]
    assert "metrics kept for later" in log
    server = start_mlflow_server(stack["backend"], stack["folder"] / "artifacts", port, workers=1)
    try:
        (run,) = runs_of(client, name)
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]
        assert run.info.status == "FINISHED"
        assert steps == list(range(400, 8001, 400))  # every evaluation arrived, none twice
    finally:
        server.stop()


@pytest.mark.parametrize(
    "fault",
    [
        "kill -9 a job, population=2",
        "Ray retries exhausted",
        "Ctrl-C of the driver",
        "Ctrl-C of a plain multirun",
        "PostgreSQL down",
    ],
)
def test_a_sweep_under_a_fault_keeps_every_promise(stack, ray_cluster, tmp_path, fault):
    """The core of `make chaos` (tests/chaos.py, every fault, several repetitions): a 2-trial
    sweep on the cluster with one fault injected at a seeded random time; afterwards nothing is
    RUNNING, every trial ended, no evaluation was logged twice, the secret is nowhere, and
    walkers.compare reports on what finished."""
    name = "fault_" + "".join(c if c.isalnum() else "_" for c in fault.lower())
    rng = random.Random(sum(map(ord, fault)))
    result = cluster_kit.run_fault(stack["kit"], ray_cluster, fault, name, tmp_path, rng)
    assert result.broken == [], f"{fault} ({result.done}): {result.broken}"
    runs = runs_of(stack["client"], name)
    if fault.startswith("kill -9 a job, population"):
        # the retry continued the killed job's 2 member runs (or, killed before any checkpoint,
        # ended them FAILED as superseded and started 2 new ones): 2 jobs x 2 members count
        assert result.done.startswith("killed job"), result.done
        assert "ran before as run(s)" in result.output  # the retry found the killed job's runs
        members = [r for r in runs if "walkers.population_member" in r.data.tags]
        current = [r for r in members if "walkers.superseded" not in r.data.tags]
        assert len(current) == 2 * 2 and all(r.info.status == "FINISHED" for r in current)
    if fault == "Ray retries exhausted":
        states = Counter(t.state.name for t in study(stack, name).trials)
        assert states["FAIL"] >= 1, states
        assert any(r.info.status == "FAILED" for r in runs)
    if fault.startswith("Ctrl-C"):  # the driver's jobs died with it: their runs ended KILLED
        assert any(r.info.status == "KILLED" for r in runs), [r.info.status for r in runs]


def test_a_ray_node_without_the_study_variable_is_named_before_anything_runs(stack, tmp_path):
    """The study's variable exported after `ray start` (or forgotten on a machine): the sweeper
    asks every node before it launches, and says which one lacks what, in one line."""
    name = "cluster_no_env"
    bare = LocalRay(nodes=1, unset=(STORAGE_ENV,)).start()
    try:
        result = run_cli(
            ["-m", "sweeps=pendulum_tiny", *TRIAL, *stores(stack, name), *on_ray(bare),
             f"hydra.sweeper.study_name={name}", f"hydra.sweep.dir={tmp_path}/sweep"],
            cwd=tmp_path,
            timeout=300,
        )  # fmt: skip
    finally:
        bare.stop()
    line = one_line_error(result)
    assert f"{STORAGE_ENV} is not set on Ray node " in line and "(node " in line
    assert "before `ray start`" in line
    assert name not in [s.study_name for s in optuna.get_all_study_summaries(stack["optuna"])]
    assert runs_of(stack["client"], name) == []
