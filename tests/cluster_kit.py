"""A cluster on loopback for the scale-out tests and `make chaos`, and the faults they inject.

- :func:`start_stack`: PostgreSQL (pgserver) whose study database only takes a password (so a
  job that did not get the secret by reference cannot report to its study) and an MLflow server
  with one worker process (the cores are the jobs' and the cluster's control plane's).
- :class:`LocalRay`: a Ray head and worker nodes, one CPU each, every port chosen free and a temp
  dir of their own; :meth:`LocalRay.stop` ends exactly the processes this cluster started (its
  daemons and workers carry a marker in their environment). ``ray stop --force`` would end every
  Ray on the machine, another suite's included.
- :data:`FAULTS` and :func:`run_fault`: a small sweep on the cluster with one fault injected at
  a time drawn from a seeded generator, then :func:`broken_promises`: what the platform promises
  after any fault (nothing RUNNING, every trial ended, no evaluation logged twice, no secret on
  disk, a report that works).
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import optuna
import psutil
from mlflow.tracking import MlflowClient
from optuna.trial import TrialState

from tests.conftest import default_sigint
from walkers.tracking.servers import MlflowServer, start_mlflow_server, start_postgres
from walkers.tuning.studies import STORAGE_ENV

RAY = str(Path(sys.executable).with_name("ray"))
#: Environment variable marking every process a :class:`LocalRay` started (daemons, workers).
MARKER = "WALKERS_TEST_CLUSTER"
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
#: A trial long enough to be hit mid-run: 6 evaluations and checkpoints.
LONGER_TRIAL = [*TRIAL, "total_steps=3000", "checkpoint_every=500", "eval_every=500"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- the stores --------------------------------------------------------------------------------
@dataclass
class Stack:
    """PostgreSQL and an MLflow server on it; both can be stopped and started again (faults)."""

    folder: Path
    secret: str  # the study database's password: it must reach no file, log or MLflow
    optuna_url: str  # with the password: what a user exports as WALKERS_OPTUNA_STORAGE
    admin_optuna_url: str  # the superuser's, no password: what the tests read studies with
    backend: str  # the MLflow server's database
    port: int
    postgres: object = None
    mlflow: MlflowServer | None = None

    @property
    def tracking(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def client(self) -> MlflowClient:
        return MlflowClient(self.tracking)

    def start_postgres(self) -> None:
        self.postgres, _ = start_postgres(self.folder / "postgres")

    def stop_postgres(self) -> None:
        self.postgres.cleanup()  # pgserver's stop: the server goes down, its data stays

    def start_mlflow(self) -> None:
        self.mlflow = start_mlflow_server(
            self.backend, self.folder / "artifacts", self.port, log_dir=self.folder, workers=1
        )

    def stop(self) -> None:
        if self.mlflow is not None:
            self.mlflow.stop()
        if self.postgres is not None:
            self.postgres.cleanup()

    def places(self) -> list[Path]:
        """Where the stack writes what it is sent: artifacts, the server's logs."""
        return [self.folder / "artifacts", *self.folder.glob("mlflow-server-*.log")]

    def study(self, name: str) -> optuna.Study:
        return optuna.load_study(study_name=name, storage=self.admin_optuna_url)


def start_stack(folder: Path) -> Stack:
    """PostgreSQL with the ``mlflow`` and ``optuna`` databases, the latter owned by a role that
    must give its password, and an MLflow server on the former."""
    server, uris = start_postgres(folder / "postgres")
    secret = f"pw-{uuid.uuid4().hex}"
    server.psql(f"CREATE ROLE walker LOGIN PASSWORD '{secret}';")
    server.psql("ALTER DATABASE optuna OWNER TO walker;")
    hba = Path(server.psql("SHOW hba_file;").split()[2])
    hba.write_text("local optuna walker scram-sha-256\n" + hba.read_text())  # first match wins
    server.psql("SELECT pg_reload_conf();")
    admin = uris["optuna"]
    stack = Stack(
        folder=folder,
        secret=secret,
        optuna_url=admin.replace("//postgres:@", f"//walker:{secret}@", 1),
        admin_optuna_url=admin,
        backend=uris["mlflow"],
        port=free_port(),
        postgres=server,
    )
    assert stack.optuna_url != admin, admin
    # Optuna's tables, created now by their owner: created by whoever reads a study first (the
    # superuser, to check a fault's outcome), they would refuse the owner
    optuna.storages.RDBStorage(stack.optuna_url).engine.dispose()
    stack.start_mlflow()
    return stack


def stores(stack: Stack, experiment: str) -> list[str]:
    """Overrides for runs on the stack; the study storage comes from the environment
    (``WALKERS_OPTUNA_STORAGE``, set by the caller), never from the command line."""
    return [
        "tracking=server",
        f"tracking.uri={stack.tracking}",
        f"tracking.experiment={experiment}",
        "optuna=postgres",
    ]


# --- Ray ---------------------------------------------------------------------------------------
class LocalRay:
    """A Ray head and ``nodes - 1`` worker nodes on loopback, one CPU each."""

    def __init__(
        self, nodes: int = 2, env: dict[str, str] | None = None, unset: tuple[str, ...] = ()
    ):
        self.nodes, self.marker = nodes, uuid.uuid4().hex
        self.temp_dir = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # sockets: short paths
        self.port = free_port()
        self.env = {
            **os.environ,
            "OMP_NUM_THREADS": "1",
            "RAY_USAGE_STATS_ENABLED": "0",
            MARKER: self.marker,
            **(env or {}),
        }
        for name in ("MLFLOW_TRACKING_URI", *unset):  # ``unset``: as if never exported there
            self.env.pop(name, None)

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def start(self) -> LocalRay:
        ports = ["--node-manager-port", "--object-manager-port", "--dashboard-agent-listen-port",
                 "--dashboard-agent-grpc-port", "--runtime-env-agent-port",
                 "--metrics-export-port"]  # fmt: skip
        for i in range(self.nodes):
            node = [RAY, "start", "--num-cpus", "1", "--disable-usage-stats"]
            node += [arg for port in ports for arg in (port, str(free_port()))]
            if i == 0:
                node += ["--head", "--port", str(self.port), "--include-dashboard=false",
                         "--temp-dir", str(self.temp_dir),
                         "--ray-client-server-port", str(free_port())]  # fmt: skip
            else:
                node += [f"--address={self.address}"]
            # the nodes start in the cluster's own folder: their workers inherit it as their
            # working directory, so a job's relative paths (work_dir's default `.walkers`)
            # land there, not in the folder pytest was started from
            done = subprocess.run(
                node,
                env=self.env,
                cwd=self.temp_dir,
                capture_output=True,
                text=True,
                timeout=180,
            )
            if done.returncode != 0:
                self.stop()
                raise RuntimeError(f"ray start failed: {(done.stdout + done.stderr)[-3000:]}")
        return self

    def processes(self) -> list[psutil.Process]:
        """Every process of this cluster: its daemons and workers carry its marker."""
        mine = []
        for process in psutil.process_iter():
            try:
                if process.environ().get(MARKER) == self.marker:
                    mine.append(process)
            except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
                pass
        return mine

    def jobs(self) -> list[psutil.Process]:
        """The worker processes running a Hydra job now (title ``ray::_run_job``): never the
        node's agents, whose titles also start with ``ray::`` and whose death ends the node."""
        jobs = []
        for process in self.processes():
            try:
                if "ray::_run_job" in " ".join(process.cmdline()):
                    jobs.append(process)
            except (psutil.NoSuchProcess, psutil.ZombieProcess):
                pass
        return jobs

    def stop(self) -> None:
        processes = self.processes()
        for process in processes:
            try:
                process.terminate()
            except psutil.NoSuchProcess:
                pass
        _, alive = psutil.wait_procs(processes, timeout=15)
        for process in alive:
            try:
                process.kill()
            except psutil.NoSuchProcess:
                pass
        shutil.rmtree(self.temp_dir, ignore_errors=True)

    def places(self) -> list[Path]:
        """Ray's session folders: its logs (the runtime-env agent's among them) and spills."""
        return [self.temp_dir]


# --- what every fault must leave true ----------------------------------------------------------
def runs_of(client: MlflowClient, experiment: str) -> list:
    found = client.get_experiment_by_name(experiment)
    if found is None:
        return []
    return client.search_runs([found.experiment_id], max_results=1000)


def files_holding(secret: str, places: list[Path]) -> list[str]:
    """Every file in ``places`` (files, and folders searched whole) whose bytes hold ``secret``."""
    found = []
    for place in map(Path, places):
        for path in [place] if place.is_file() else place.rglob("*"):
            try:
                if path.is_file() and secret.encode() in path.read_bytes():
                    found.append(str(path))
            except OSError:  # a socket, a file that went away
                pass
    return found


def broken_promises(
    stack: Stack, name: str, secret_places: list[Path], outputs: list[str], compare: bool = True
) -> list[str]:
    """What the platform promises after any fault, for experiment and study ``name``; returns
    what does not hold (empty: all kept)."""
    broken, client = [], stack.client
    runs = runs_of(client, name)
    running = [r.info.run_id for r in runs if r.info.status == "RUNNING"]
    if running:
        broken.append(f"{len(running)} runs RUNNING")
    trials = stack.study(name).trials if name in optuna.get_all_study_names(
        stack.admin_optuna_url) else []  # fmt: skip
    states = Counter(t.state.name for t in trials)
    if states.get("RUNNING") or states.get("WAITING"):
        broken.append(f"trials not ended: {dict(states)}")
    for run in runs:
        if "walkers.kind" in run.data.tags:
            continue
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]
        if len(steps) != len(set(steps)):
            broken.append(f"run {run.info.run_id} logged an evaluation twice: {sorted(steps)}")
    for run in runs:  # MLflow params and tags
        values = list(run.data.params.values()) + list(run.data.tags.values())
        if any(stack.secret in str(v) for v in values):
            broken.append(f"the secret is in run {run.info.run_id}'s params or tags")
    if held := files_holding(stack.secret, secret_places):
        broken.append(f"the secret is on disk: {held[:3]}")
    if any(stack.secret in output for output in outputs):
        broken.append("the secret is in the console output")
    trained = [r for r in runs if "walkers.kind" not in r.data.tags]
    if compare and any(r.info.status == "FINISHED" for r in trained):
        report = subprocess.run(
            [sys.executable, "-m", "walkers.compare", "env=pendulum", "algos=[td3]",
             f"tracking.uri={stack.tracking}", f"tracking.experiment={name}",
             f"out={stack.folder / 'reports' / name}"],
            capture_output=True, text=True, timeout=600, env=_env(),
        )  # fmt: skip
        if report.returncode != 0:
            broken.append(f"walkers.compare failed: {report.stderr.strip()[-300:]}")
    return broken


def _env(**extra: str) -> dict[str, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **extra}
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


# --- faults ------------------------------------------------------------------------------------
@dataclass
class Sweep:
    """A sweep process on the cluster, with its output gathered as it runs."""

    stack: Stack
    name: str
    command: list[str]
    cwd: Path
    process: subprocess.Popen | None = None
    output: list[str] = field(default_factory=list)

    def start(self) -> Sweep:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "walkers.train", *self.command],
            cwd=self.cwd,
            env=_env(**{STORAGE_ENV: self.stack.optuna_url}),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            preexec_fn=default_sigint,  # Ctrl-C as in a terminal
        )
        return self

    def wait(self, timeout: float = 900) -> int:
        try:
            out, _ = self.process.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            out, _ = self.process.communicate()
        self.output.append(out)
        return self.process.returncode

    def alive(self) -> bool:
        return self.process.poll() is None

    def wait_for_training(self, timeout: float = 300) -> None:
        """Until a training run of the sweep is RUNNING with an evaluation logged."""
        client, deadline = self.stack.client, time.monotonic() + timeout
        while time.monotonic() < deadline and self.alive():
            for run in runs_of(client, self.name):
                if run.info.status == "RUNNING" and "eval/return_mean" in run.data.metrics:
                    return
            time.sleep(0.5)
        raise AssertionError(f"no training run of {self.name} evaluated in time")


def sweep_command(
    stack: Stack, ray: LocalRay, name: str, folder: Path, *extra: str, study: bool = True
) -> list[str]:
    """A 2-trial study of ``name`` on the cluster; ``study=False``: a plain multirun of 2 jobs
    (seeds 0 and 1) instead, for what a study does not run (populations)."""
    what = (
        ["sweeps=pendulum_tiny", f"hydra.sweeper.study_name={name}", "hydra.sweeper.n_trials=2",
         "pruner=none", "optuna.heartbeat_interval=1", "optuna.grace_period=4"]
        if study else ["algo=td3", "env=pendulum", "seed=0,2"]
    )  # fmt: skip
    return [
        "-m", *what, *LONGER_TRIAL, *stores(stack, name),
        "hydra/launcher=ray_cluster", f"hydra.launcher.ray.init.address={ray.address}",
        f"work_dir={folder / '.walkers'}", f"hydra.sweep.dir={folder / 'sweep'}", *extra,
    ]  # fmt: skip


def kill_a_job(sweep: Sweep, ray: LocalRay, rng: random.Random) -> str:
    sweep.wait_for_training()
    time.sleep(rng.uniform(0, 3))
    jobs = ray.jobs()
    if not jobs:
        return "no job running to kill"
    victim = rng.choice(jobs)
    victim.send_signal(signal.SIGKILL)
    return f"killed job pid {victim.pid}"


def kill_the_sweeper(sweep: Sweep, ray: LocalRay, rng: random.Random) -> str:
    sweep.wait_for_training()
    time.sleep(rng.uniform(0, 3))
    sweep.process.send_signal(signal.SIGKILL)  # its Ray jobs end with it (driver fate-sharing)
    sweep.wait(60)
    return "killed the sweeper; a new one finishes the study"


def interrupt_the_sweeper(sweep: Sweep, ray: LocalRay, rng: random.Random) -> str:
    sweep.wait_for_training()
    time.sleep(rng.uniform(0, 3))
    sweep.process.send_signal(signal.SIGINT)
    return "Ctrl-C to the sweeper"


def _outage(stop: Callable[[], None], start: Callable[[], None], rng: random.Random) -> float:
    stop()
    down = rng.uniform(3, 8)
    time.sleep(down)
    start()
    return down


def mlflow_outage(sweep: Sweep, ray: LocalRay, rng: random.Random) -> str:
    sweep.wait_for_training()
    time.sleep(rng.uniform(0, 3))
    down = _outage(sweep.stack.mlflow.stop, sweep.stack.start_mlflow, rng)
    return f"MLflow server down {down:.1f} s"


def postgres_outage(sweep: Sweep, ray: LocalRay, rng: random.Random) -> str:
    sweep.wait_for_training()
    time.sleep(rng.uniform(0, 3))
    down = _outage(sweep.stack.stop_postgres, sweep.stack.start_postgres, rng)
    return f"PostgreSQL down {down:.1f} s"


@dataclass(frozen=True)
class Fault:
    """One fault of the matrix: how it is injected, what the sweep runs with, how it ends."""

    inject: Callable[[Sweep, LocalRay, random.Random], str]
    overrides: tuple[str, ...] = ()
    sweep_succeeds: bool = True  # False: the sweep ends with an error, its trials FAIL
    finish_with_new_sweeper: bool = False
    study: bool = True  # False: a plain multirun (a population is no study's trial)


FAULTS: dict[str, Fault] = {
    "kill -9 a job": Fault(kill_a_job),
    "kill -9 a job, population=2": Fault(kill_a_job, ("population=2",), study=False),
    "kill -9 a job, seeds_per_trial=2": Fault(kill_a_job, ("seeds_per_trial=2",)),
    "kill -9 the sweeper": Fault(kill_the_sweeper, finish_with_new_sweeper=True),
    "MLflow server down": Fault(mlflow_outage),
    "PostgreSQL down": Fault(postgres_outage),
    "Ray retries exhausted": Fault(
        kill_a_job, ("hydra.launcher.ray.remote.max_retries=0",), sweep_succeeds=False
    ),
    "Ctrl-C of the driver": Fault(interrupt_the_sweeper, sweep_succeeds=False),
    "Ctrl-C of a plain multirun": Fault(interrupt_the_sweeper, sweep_succeeds=False, study=False),
}


@dataclass
class FaultResult:
    done: str  # what was injected
    broken: list[str]  # promises broken afterwards (empty: all kept)
    output: str  # the sweep's console (its jobs' logs come back through Ray)


def run_fault(
    stack: Stack, ray: LocalRay, fault_name: str, name: str, folder: Path, rng: random.Random
) -> FaultResult:
    """A 2-trial sweep on the cluster with ``fault_name`` injected, and what came of it."""
    fault = FAULTS[fault_name]
    folder.mkdir(parents=True, exist_ok=True)
    command = sweep_command(stack, ray, name, folder, *fault.overrides, study=fault.study)
    sweep = Sweep(stack, name, command, folder).start()
    broken = []
    try:
        done = fault.inject(sweep, ray, rng)
    except AssertionError as e:
        done = f"not injected: {e}"
        broken.append(done)
    if fault.finish_with_new_sweeper:
        sweep = Sweep(stack, name, command, folder, output=sweep.output).start()
    code = sweep.wait()
    if (code == 0) != fault.sweep_succeeds:
        broken.append(f"the sweep exited {code}: {sweep.output[-1][-1500:]}")
    if fault.study and name not in optuna.get_all_study_names(stack.admin_optuna_url):
        broken.append(f"no study {name}: {''.join(sweep.output)[-1500:]}")
    elif fault.sweep_succeeds and fault.study:
        trials = stack.study(name).trials
        ended = [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
        if len(ended) < 2:
            broken.append(f"{len(ended)} of n_trials=2 trials complete: {trials}")
    broken += broken_promises(stack, name, [folder, *ray.places(), *stack.places()], sweep.output)
    return FaultResult(done, broken, "".join(sweep.output))
