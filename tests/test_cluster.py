"""Scale-out with the real parts: a Ray cluster on loopback (a head and a worker node), PostgreSQL
(pgserver) behind Optuna and an MLflow tracking server, all started here (`make test-cluster`).

The same commands as on one machine, with ``hydra/launcher=ray_cluster tracking=server
optuna=postgres``: sweeps with several seeds per trial across the nodes, two sweepers on one
study, a job's worker killed mid-trial, a sweeper killed mid-trial, runs evaluated, collected
and resumed from another directory, the submitit launcher, and bad addresses refused.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import optuna
import psutil
import pytest
from mlflow.tracking import MlflowClient
from optuna.trial import TrialState

from tests.conftest import one_line_error, run_cli, spawn_cli
from walkers.tracking.servers import start_mlflow_server, start_postgres

pytestmark = pytest.mark.cluster

RAY = str(Path(sys.executable).with_name("ray"))
#: A sweep trial in seconds: TD3 on Pendulum, small nets, learning from step 200.
TRIAL = [
    "algo.hidden_sizes=[32,32]",
    "env.learning_starts=200",
    "total_steps=600",
    "eval_every=300",
    "eval_episodes=1",
    "checkpoint_every=300",
    "pruning.warmup_steps=300",
    "progress=false",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """PostgreSQL with the mlflow and optuna databases, an MLflow server on it."""
    folder = tmp_path_factory.mktemp("stack")
    server, uris = start_postgres(folder / "postgres")
    mlflow = start_mlflow_server(uris["mlflow"], folder / "artifacts", free_port(), log_dir=folder)
    yield {
        "tracking": mlflow.url,
        "optuna": uris["optuna"],
        "client": MlflowClient(mlflow.url),
        "backend": uris["mlflow"],
        "folder": folder,
    }
    mlflow.stop()
    server.cleanup()


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory):
    """A head and a worker node on loopback, one CPU each (so jobs spread over both)."""
    folder = tmp_path_factory.mktemp("ray")
    port = free_port()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0"}
    env.pop("MLFLOW_TRACKING_URI", None)
    common = ["--num-cpus", "1", "--disable-usage-stats"]
    head = [RAY, "start", "--head", "--port", str(port), "--include-dashboard=false", *common]
    subprocess.run(head, cwd=folder, env=env, check=True, capture_output=True, timeout=180)
    worker = [RAY, "start", f"--address=127.0.0.1:{port}", *common]
    subprocess.run(worker, cwd=folder, env=env, check=True, capture_output=True, timeout=180)
    yield f"127.0.0.1:{port}"
    subprocess.run([RAY, "stop", "--force"], capture_output=True, timeout=120)


def stores(stack, experiment: str) -> list[str]:
    return [
        "tracking=server",
        f"tracking.uri={stack['tracking']}",
        f"tracking.experiment={experiment}",
        "optuna=postgres",
        f"optuna.storage='{stack['optuna']}'",
    ]


def on_ray(address: str) -> list[str]:
    return ["hydra/launcher=ray_cluster", f"hydra.launcher.ray.init.address={address}"]


def runs_of(client: MlflowClient, experiment: str) -> list:
    experiment_id = client.get_experiment_by_name(experiment).experiment_id
    return client.search_runs([experiment_id], max_results=1000)


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
    ok(
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


LONGER_TRIAL = [*TRIAL, "total_steps=3000", "checkpoint_every=500", "eval_every=500"]


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
        jobs = [p for p in psutil.process_iter(["cmdline"]) if "ray::_run_job" in " ".join(
            p.info["cmdline"] or [])]  # fmt: skip
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
    server = start_mlflow_server(stack["backend"], stack["folder"] / "artifacts", port)
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
        server = start_mlflow_server(stack["backend"], stack["folder"] / "artifacts", port)
        log = training.communicate(timeout=600)[0]
    finally:
        if training.poll() is None:
            training.kill()
        server.stop()
    assert training.returncode == 0, log[-3000:]
    assert "metrics kept for later" in log
    server = start_mlflow_server(stack["backend"], stack["folder"] / "artifacts", port)
    try:
        (run,) = runs_of(client, name)
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]
        assert run.info.status == "FINISHED"
        assert steps == list(range(400, 8001, 400))  # every evaluation arrived, none twice
    finally:
        server.stop()
