"""A terminated run ends KILLED with a checkpoint it can resume from."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import pytest

from tests.conftest import (
    all_runs,
    default_sigint,
    interrupt_group_once_checkpointed,
    run_cli,
    signal_once_checkpointed,
    spawn_cli,
    wait_for_uploaded_checkpoint,
)
from walkers import PROJECT_ROOT
from walkers.training.run import read_checkpoint

pytestmark = pytest.mark.faults  # `make test-faults`, beside `make test` in CI

#: A run far longer than any test waits: it is stopped by a signal after its first evaluation.
LONG_RUN = [
    "env=pendulum",
    "total_steps=100000",
    "eval_every=500",
    "eval_episodes=1",
    "checkpoint_every=100000",
    "algo.learning_starts=100",
    "progress=false",
]


def test_sigterm_saves_a_checkpoint_and_ends_killed(store):
    args = [*LONG_RUN, *store["overrides"]]
    code, _, stderr = signal_once_checkpointed(args, store["path"], "best.pt", signal.SIGTERM)
    assert code == 130, stderr[-2000:]
    (run,) = all_runs(store["client"])
    step = killed_with_checkpoint_then_resumed(store, run)
    assert 500 <= step < 100000


def killed_with_checkpoint_then_resumed(store, run) -> int:
    """``run`` ended KILLED with a ``last.pt``; ``resume=`` continues it to FINISHED. Returns the
    checkpoint's step."""
    assert run.info.status == "KILLED"
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    step = read_checkpoint(path)["trainer"]["step"]
    resumed = run_cli(
        [f"resume={run.info.run_id}", f"total_steps={step + 200}", *store["overrides"]],
        cwd=store["path"],
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (again,) = all_runs(store["client"])
    assert again.info.status == "FINISHED"
    return step


def test_a_terminated_population_resumes_together(store):
    args = [*LONG_RUN, "population=2", "algo.hidden_sizes=[16,16]", *store["overrides"]]
    code, stdout, stderr = signal_once_checkpointed(args, store["path"], "best.pt", signal.SIGTERM)
    assert code == 130, stderr[-2000:]
    runs = sorted(all_runs(store["client"]), key=lambda r: r.data.params["seed"])  # member order
    assert [r.info.status for r in runs] == ["KILLED", "KILLED"]
    steps = {
        read_checkpoint(
            store["client"].download_artifacts(
                r.info.run_id, "checkpoints/last.pt", str(store["path"] / r.info.run_id)
            )
        )["trainer"]["step"]
        for r in runs
    }
    assert len(steps) == 1  # both members stopped at the same step
    (step,) = steps
    ids = ",".join(r.info.run_id for r in runs)
    assert f"resume=[{ids}]" in stdout  # the command that continues them is printed

    resumed = run_cli(
        [f"resume=[{ids}]", f"total_steps={step + 200}", *store["overrides"]], cwd=store["path"]
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert [r.info.status for r in all_runs(store["client"])] == ["FINISHED", "FINISHED"]


def test_signals_to_the_whole_group_while_it_ends_leave_it_killed_with_its_checkpoint(store):
    """`timeout -s TERM 75 make train`, `scancel`, `kill -TERM -<pgid>`: make and python both get
    the signal, make forwards another, a supervisor insists. Here: SIGTERM to the process group
    every 50 ms from the first one until the process is gone."""
    args = [
        *LONG_RUN,
        "save_buffer=true",
        *store["overrides"],
        f"hydra.run.dir={store['path']}/out",
    ]
    proc = subprocess.Popen(
        ["make", "-s", "-C", str(PROJECT_ROOT), "train", f"ARGS={' '.join(args)}"],
        cwd=store["path"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"},
    )
    try:
        wait_for_uploaded_checkpoint(proc, store["path"], "best.pt")
        deadline = time.monotonic() + 180
        while proc.poll() is None and time.monotonic() < deadline:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert "Traceback" not in stderr, stderr[-3000:]
    assert stderr.count("already stopping") <= 1, stderr[-3000:]
    (run,) = all_runs(store["client"])
    assert f"continue it: python -m walkers.train resume={run.info.run_id}" in stdout + stderr
    killed_with_checkpoint_then_resumed(store, run)


def test_ctrl_c_under_make_train_ends_on_walkers_line_without_make_s_error(store):
    """Ctrl-C in the terminal under `make train` (SIGINT to make, its shell and python): the last
    line is walkers' `interrupted: ...`, with no `make: *** [...] Error 130` after it, and make
    still ends by the signal; another failure stays make's error, with its own status."""

    def make_train(*args: str, **popen) -> subprocess.Popen:
        args = [*args, *store["overrides"], f"hydra.run.dir={store['path']}/out"]
        return subprocess.Popen(
            # -o: the .venv running this test is the one to train with (no reinstall)
            ["make", "-s", "-C", str(PROJECT_ROOT), "-o", ".venv/.installed", "train",
             f"ARGS={' '.join(args)}"],
            cwd=store["path"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"},
            preexec_fn=default_sigint,
            **popen,
        )  # fmt: skip

    proc = make_train(*LONG_RUN, start_new_session=True)
    stderr = interrupt_group_once_checkpointed(proc, store["path"], "best.pt")
    assert proc.returncode == -signal.SIGINT, stderr[-3000:]
    assert stderr.strip().splitlines()[-1].startswith("interrupted: MLflow run(s)"), stderr[-3000:]
    assert "Error 130" not in stderr

    failed = make_train(*LONG_RUN, "total_steps=0")
    _, stderr = failed.communicate(timeout=120)
    assert failed.returncode == 2 and "total_steps=0 is not allowed" in stderr, stderr[-3000:]
    assert "] Error 2" in stderr


def test_ctrl_c_of_a_keyed_joblib_multirun_ends_its_runs_and_the_same_command_continues_them(
    store,
):
    """The README's twin runs: a plain multirun on joblib with job keys of the user's own. Joblib
    stops its workers with the driver, before they can end their runs; the driver ends them
    KILLED, found by the multirun they belong to whatever their keys, and the same command
    continues each from its last checkpoint."""
    args = [
        "-m",
        "algo=td3",
        "env=pendulum",
        "seed=0,1",
        "job_key=mine/${seed}",
        "total_steps=3000",
        "eval_every=500",
        "eval_episodes=1",
        "checkpoint_every=500",
        "algo.learning_starts=100",
        "algo.hidden_sizes=[16,16]",
        "progress=false",
        "torch_threads=1",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        *store["overrides"],
    ]
    proc = spawn_cli(args, cwd=store["path"], new_session=True)
    try:
        deadline = time.monotonic() + 180
        while len(list((store["path"] / "mlartifacts").rglob("last.pt"))) < 2:  # both training
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            assert time.monotonic() < deadline, "no two checkpoints within 180 s"
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in the terminal: the driver and its workers
        _, stderr = proc.communicate(timeout=180)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr[-3000:]
    assert "interrupted: multirun stopped" in stderr and "Traceback" not in stderr, stderr[-3000:]
    runs = all_runs(store["client"])
    assert sorted(r.data.tags["walkers.job_key"] for r in runs) == ["mine/0", "mine/1"]
    assert {r.info.status for r in runs} <= {"KILLED", "FINISHED"}, [r.info for r in runs]
    assert any(r.info.status == "KILLED" for r in runs)

    again = run_cli(args, cwd=store["path"])
    assert again.returncode == 0, again.stderr[-3000:]
    continued = all_runs(store["client"])
    assert {r.info.run_id for r in continued} == {r.info.run_id for r in runs}  # no new runs
    assert {r.info.status for r in continued} == {"FINISHED"}
    assert "continuing it from its last checkpoint" in again.stdout + again.stderr
