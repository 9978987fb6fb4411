"""Shared test helpers: compose the real config with tiny overrides, temp MLflow stores, the CLI."""

from __future__ import annotations

import atexit
import functools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import get_class
from mlflow.tracking import MlflowClient

from walkers import PROJECT_ROOT
from walkers.agents.base import Transition
from walkers.agents.declarations.schemas import SCHEMAS, tiny_overrides
from walkers.agents.factory import defaults_for
from walkers.data.datasets import OfflineData
from walkers.data.episodes import Episode

# `make test` runs one worker per core: each (and every command it spawns) gets one thread, as
# two-thread torch pools on two busy cores slow each other down several times over. A file run on
# its own gets one thread too, so that it trains the same runs as in the suite: the learning tests'
# results depend on the thread count (a sum's order), and a DT that learns its targets with one
# thread was seen to miss them with two.
os.environ["OMP_NUM_THREADS"] = "1"
torch.set_num_threads(1)

CONF_DIR = str(PROJECT_ROOT / "conf")

#: Overrides that make any run tiny: short budget, quick evals, early learning.
TINY = [
    "total_steps=600",
    "eval_every=300",
    "eval_episodes=1",
    "checkpoint_every=300",
    "log_every=100",
    "progress=false",
]


def tiny(algo: str) -> list[str]:
    """The overrides that make a tiny run of ``algo`` learn: its declaration's ``TINY``."""
    return tiny_overrides(SCHEMAS[algo])


#: every algorithm that learns from env steps, from the declarations (algo=dt learns offline)
ONLINE = [name for name, schema in SCHEMAS.items() if not get_class(schema.AGENT).offline]
#: A PPO that updates within a tiny run: rollouts of 128 steps, 2 epochs of 4 minibatches.
PPO_TINY = tiny("ppo")

#: The metrics every online run logs (docs/training.md, the evaluation protocol).
DESIGN_METRICS = {
    "eval/return_mean",
    "eval/return_std",
    "final/return_mean",
    "final/return_last10",
    "final/auc",
    "final/steps_to_threshold",
    "perf/sps",
}


def compose_cfg(overrides: list[str], config_name: str = "train"):
    """The real config of an entrypoint (``train``, ``evaluate``, ``compare``) with overrides."""
    with initialize_config_dir(config_dir=CONF_DIR):
        return compose(config_name=config_name, overrides=overrides)


@functools.cache
def _store_template() -> Path:
    """An MLflow sqlite file with its schema created, one per test process: MLflow takes
    seconds to migrate a new one, and every test store would pay them in its first command."""
    folder = Path(tempfile.mkdtemp(prefix="walkers-store-template-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    MlflowClient(f"sqlite:///{folder / 'mlflow.db'}").search_experiments()
    return folder / "mlflow.db"


@pytest.fixture(scope="session")
def _empty_store_file() -> Path:
    return _store_template()


def new_store(path: Path, template: Path | None = None) -> dict:
    """A sqlite MLflow store and scratch dir in ``path``: overrides pointing runs there. A new
    store's file is a copy of an empty one (``template``, by default this process's)."""
    path.mkdir(parents=True, exist_ok=True)
    if not (path / "mlflow.db").exists():
        shutil.copyfile(template or _store_template(), path / "mlflow.db")
    uri = f"sqlite:///{path / 'mlflow.db'}"
    return {
        "uri": uri,
        "client": MlflowClient(uri),
        "overrides": [f"tracking.uri={uri}", f"work_dir={path / 'work'}"],
        "path": path,
    }


@pytest.fixture
def store(tmp_path, _empty_store_file):
    return new_store(tmp_path, _empty_store_file)


def run_cli(
    args: list[str],
    cwd: Path,
    timeout: float = 300,
    module: str = "walkers.train",
    env_overrides: dict[str, str] | None = None,
    **popen,
) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS`` (default: walkers.train) in a subprocess, as a user would."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env_overrides or {})}
    env.pop("MLFLOW_TRACKING_URI", None)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **popen,
    )


def default_sigint() -> None:
    """``preexec_fn`` for a child that is to get Ctrl-C as in a terminal, even where the tests run
    in the background: a shell without job control starts background commands with SIGINT
    ignored, the ignore is inherited, and a make started so keeps it (it ends 0, not by the
    signal)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def spawn_cli(
    args: list[str], cwd: Path, merge_output: bool = False, new_session: bool = False
) -> subprocess.Popen:
    """Start ``python -m walkers.train ARGS`` in the background (to signal or kill it);
    ``merge_output``: stderr into stdout (one log to read); ``new_session``: in a process group
    of its own (to signal it with its workers)."""
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    return subprocess.Popen(
        [sys.executable, "-m", "walkers.train", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT if merge_output else subprocess.PIPE,
        text=True,
        start_new_session=new_session,
    )


def wait_for_uploaded_checkpoint(
    proc: subprocess.Popen, store_path: Path, name: str, timeout: float = 120
) -> None:
    """Block until the run has uploaded ``checkpoints/<name>`` to the store's artifacts."""
    deadline = time.monotonic() + timeout
    while not list((store_path / "mlartifacts").rglob(name)):
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.monotonic() < deadline, f"no {name} within {timeout} s"
        time.sleep(0.2)


def interrupt_group_once_checkpointed(
    proc: subprocess.Popen, store_path: Path, checkpoint: str
) -> str:
    """Ctrl-C to ``proc``'s whole process group (as a terminal sends it: a ``make`` and its
    training, a population and its env workers) once ``checkpoint`` is uploaded; its stderr."""
    try:
        wait_for_uploaded_checkpoint(proc, store_path, checkpoint)
        os.killpg(proc.pid, signal.SIGINT)
        return proc.communicate(timeout=180)[1]
    finally:
        proc.kill()


def signal_once_checkpointed(
    args: list[str], store_path: Path, checkpoint: str, sig: int
) -> tuple[int, str, str]:
    """Start a training CLI, send it ``sig`` once it has uploaded ``checkpoint``, wait for it.

    Returns ``(exit code, stdout, stderr)``.
    """
    proc = spawn_cli(args, cwd=store_path)
    try:
        wait_for_uploaded_checkpoint(proc, store_path, checkpoint)  # it is training
        proc.send_signal(sig)
        # ending takes a last checkpoint and the run's status; on a loaded machine a sqlite store
        # can stay locked for a while (the run retries, up to its store patience)
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        proc.kill()
    return proc.returncode, stdout, stderr


#: ``python -c`` this, then a signal's number, N, a callable (``module:Class.attr``) and
#: walkers.train's arguments: the process sends itself the signal right after its Nth call of
#: that callable (an Adam step: the signal lands inside an update).
_SIGNAL_AFTER_A_CALL = """
import importlib, os, runpy, sys
sig, at, where, calls = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], 0
module, path = where.split(":")
*owners, name = path.split(".")
owner = importlib.import_module(module)
for part in owners:
    owner = getattr(owner, part)
called = getattr(owner, name)
def call(*args, **kwargs):
    global calls
    out = called(*args, **kwargs)
    calls += 1
    if calls == at:
        os.kill(os.getpid(), sig)
    return out
setattr(owner, name, call)
sys.argv = ["walkers.train", *sys.argv[4:]]
runpy.run_module("walkers.train", run_name="__main__")
"""


def run_device_script(script: str, tmp_path: Path, **settings: str) -> subprocess.CompletedProcess:
    """``bash benchmarks/SCRIPT`` as a lent GPU's call runs it, tried on the CPU: its settings
    by environment variable, with ``DEVICE=cpu``, ``SETUP=0`` (no wheels to install) and
    ``OUT`` in ``tmp_path``."""
    env = {**os.environ, "OUT": str(tmp_path / "out"), "DEVICE": "cpu", "SETUP": "0", **settings}
    return subprocess.run(
        ["bash", f"benchmarks/{script}"],
        cwd=PROJECT_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def run_cli_signalled_inside_an_update(
    args: list[str], cwd: Path, after_adam_steps: int, sig: int = 2, env_overrides=None
) -> subprocess.CompletedProcess:
    """``python -m walkers.train ARGS`` that receives ``sig`` (a real one, SIGINT by default)
    from itself right after its ``after_adam_steps``-th optimizer step."""
    return run_cli_signalled_after(
        args, cwd, "torch.optim:Adam.step", after_adam_steps, sig, env_overrides
    )


def run_cli_signalled_after(
    args: list[str], cwd: Path, where: str, calls: int, sig: int = 2, env_overrides=None
) -> subprocess.CompletedProcess:
    """``python -m walkers.train ARGS`` that receives ``sig`` (a real one, SIGINT by default)
    from itself right after its ``calls``-th call of ``where`` (``module:Class.attr``)."""
    return subprocess.run(
        [sys.executable, "-c", _SIGNAL_AFTER_A_CALL, str(sig), str(calls), where, *args],
        cwd=cwd,
        env={**os.environ, **(env_overrides or {})},
        capture_output=True,
        text=True,
        timeout=300,
    )


def pendulum_report(store_overrides: list[str], algos: list[str], out: Path):
    """``walkers.compare`` of ``algos`` on Pendulum, from the store the overrides name, into
    ``out`` (200 bootstrap resamples: enough for a test): (comparison, out, plots)."""
    from walkers.analysis.comparison import compare

    overrides = [*store_overrides, "env=pendulum", f"algos=[{','.join(algos)}]", f"out={out}"]
    return compare(compose_cfg([*overrides, "n_resamples=200"], config_name="compare"))


def all_runs(client: MlflowClient) -> list:
    """Every run in every experiment of a store (empty for a store never written to)."""
    return client.search_runs([e.experiment_id for e in client.search_experiments()])


def one_line_error(result: subprocess.CompletedProcess, code: int = 2) -> str:
    """The single ``error: ...`` line of a command that must fail with exit ``code`` (2: bad
    input) and no traceback."""
    assert result.returncode == code, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr[-2000:]
    return lines[0]


def metric_steps(client: MlflowClient, run_id: str, key: str) -> list[int]:
    return [m.step for m in client.get_metric_history(run_id, key)]


def tiny_offline_data() -> OfflineData:
    """Three 12-step episodes of Pendulum shapes (3-d states, 1-d actions in [-2, 2]), random."""
    rng = np.random.default_rng(0)
    steps = 12
    episodes = [
        Episode(
            rng.normal(size=(steps + 1, 3)).astype(np.float32),
            rng.uniform(-2, 2, size=(steps, 1)).astype(np.float32),
            rng.normal(size=steps).astype(np.float32),
            np.zeros(steps, bool),
            np.arange(steps) == steps - 1,
        )
        for _ in range(3)
    ]
    return OfflineData("tiny", "Pendulum-v1", episodes, None, None)


def feed_members(
    agent, steps: int = 60, rewards=(1.0, -1.0, 0.5), terminate_every: int | None = None
) -> None:
    """``steps`` made-up transitions for each member of an off-policy ``agent`` (acting with
    exploration, updating after each): member i's reward is ``rewards[i]``, episodes are cut by
    a time limit every 20 steps and, with ``terminate_every``, end every that many steps."""
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(agent.population, agent.obs_dim))
    for t in range(steps):
        actions = agent.act_population(obs, explore=True)
        nxt = rng.normal(size=obs.shape)
        terminated = terminate_every is not None and t % terminate_every == terminate_every - 1
        agent.observe_population(
            [
                Transition(obs[i], actions[i], float(rewards[i]), nxt[i], terminated, t % 20 == 19)
                for i in range(agent.population)
            ]
        )
        agent.update()
        obs = nxt


def filled_agent(cls, population: int = 1, device: str = "cpu", **settings):
    """A small off-policy agent of ``cls`` (5-d observations, 2-d actions, seed 3) holding the
    same 200 made-up transitions per member, not yet updated: two built alike update alike, so
    a variant (``settings``: compile, capture, ...) can be held to the eager one."""
    small = {"hidden_sizes": [32, 32], "batch_size": 32, "learning_starts": 0, "buffer_size": 500}
    obs_dim, act_dim = 5, 2
    agent = cls(
        obs_dim,
        [-2.0] * act_dim,
        [2.0] * act_dim,
        population=population,
        seed=3,
        device=device,
        **defaults_for(cls, **(small | settings)),
    )
    rng = np.random.default_rng(0)
    for t in range(200):
        obs, nxt = rng.normal(size=(2, population, obs_dim)).astype(np.float32)
        action = rng.uniform(-2, 2, (population, act_dim)).astype(np.float32)
        agent.observe_population(
            [
                Transition(obs[i], action[i], float(rng.normal()), nxt[i], t % 50 == 49, False)
                for i in range(population)
            ]
        )
    return agent


#: What a run, a sweep or a report writes in its working directory (``make clean`` removes them).
RUN_OUTPUTS = ("mlflow.db", "mlruns", "mlartifacts", "outputs", "multirun", ".walkers",
               "reports", "optuna.db")  # fmt: skip
_OUTPUTS_BEFORE = {name for name in RUN_OUTPUTS if (PROJECT_ROOT / name).exists()}


def pytest_sessionfinish(session, exitstatus):
    """Tests write only to temporary folders: a run output that appeared in the checkout while
    the suite ran fails it (each test runs its commands in its own ``tmp_path``)."""
    if hasattr(session.config, "workerinput"):
        return  # a pytest-xdist worker: the controller checks once, after all of them
    new = sorted(n for n in RUN_OUTPUTS if (PROJECT_ROOT / n).exists())
    new = [n for n in new if n not in _OUTPUTS_BEFORE]
    if new:
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        reporter.write_line(
            f"error: the tests wrote {', '.join(new)} into {PROJECT_ROOT}", red=True
        )
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
