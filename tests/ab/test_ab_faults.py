"""A/B studies under faults: a kill -9 of the driver and a SIGTERM to the whole process group,
then the same command again (split from test_ab.py so the two run on separate workers)."""

from __future__ import annotations

import collections
import os
import re
import signal
import time

import pytest

from tests.conftest import all_runs, run_cli, spawn_cli
from tests.study_kit import OBVIOUS, OBVIOUS_TD3, export, ingest, job_runs, study, study_run
from walkers.tracking.names import LOGGED_THROUGH_TAG

pytestmark = pytest.mark.faults  # `make test-faults`, beside `make test` in CI


def wait_for_a_job(store, proc, status: str, logged_below: int | None = None) -> None:
    """Block until a job of the study has a run of ``status`` (FINISHED: the study is under way;
    RUNNING: a job is training), with ``logged_below`` one that has logged some steps and fewer
    than that (far from its end, where its last flush comes just before FINISHED); failing if
    the study ends or nothing comes in 4 minutes."""

    def found(run) -> bool:
        if run.info.status != status:
            return False
        mark = run.data.tags.get(LOGGED_THROUGH_TAG)
        return logged_below is None or (mark is not None and int(mark) < logged_below)

    deadline = time.monotonic() + 240
    while not any(found(r) for r in job_runs(store)):
        assert proc.poll() is None, proc.communicate()[0][-3000:]
        assert time.monotonic() < deadline
        time.sleep(0.2)


@pytest.mark.parametrize("launcher", ["basic", "joblib"])
def test_a_rerun_after_kill_9_of_the_driver_finishes_every_seed_once(store, launcher):
    # jobs long enough that one is caught between its first checkpoint and its middle however
    # fast the cores (at 2,000 steps a REINFORCE job on idle cores was in that window for a
    # fraction of a second, and every job of a study could slip past the polling)
    args = study(
        store,
        *OBVIOUS,
        "total_steps=10000",
        "checkpoint_every=1000",
        "eval_every=1000",
        f"hydra/launcher={launcher}",
        "hydra.launcher.n_jobs=2" if launcher == "joblib" else "progress=false",
    )
    proc = spawn_cli(args, cwd=store["path"], new_session=True)
    try:
        wait_for_a_job(store, proc, "FINISHED")
        # the next one under way (on loaded cores it starts late) and far from done, then the
        # driver and its workers die together, as in a reboot
        wait_for_a_job(store, proc, "RUNNING", logged_below=5000)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.communicate()
    left = collections.Counter(r.info.status for r in job_runs(store))
    assert left["RUNNING"] >= 1, left  # what the kill left behind
    partly_done = {
        r.data.tags["walkers.job_key"]
        for r in job_runs(store)
        if r.info.status == "RUNNING" and LOGGED_THROUGH_TAG in r.data.tags
    }

    result = run_cli(args, cwd=store["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    # the round's cost said before it starts, the killed jobs' remaining steps included
    assert "study 't', look 1: about " in result.stdout + result.stderr
    # the most work left goes first: the jobs partly done are launched after every fresh one
    launched = re.findall(r"#\d+ : .*job_key=(\S+)", result.stdout + result.stderr)
    assert partly_done and set(launched[-len(partly_done) :]) == partly_done, launched
    runs = job_runs(store)
    finished = [r.data.tags["walkers.job_key"] for r in runs if r.info.status == "FINISHED"]
    assert len(finished) == len(set(finished)) == 10, finished  # every seed once, none twice
    for run in runs:  # a run killed before its first checkpoint was superseded by a new one
        assert run.info.status == "FINISHED" or "walkers.superseded" in run.data.tags, run.info
    assert sorted(int(k.rsplit("/", 1)[1]) for k in finished if "/short/" in k) == [0, 1, 2, 3, 4]
    superseded = any("walkers.superseded" in r.data.tags for r in runs)
    assert "continuing it from its last checkpoint" in result.stdout + result.stderr or superseded
    assert study_run(store).info.status == "FINISHED"


def test_a_population_job_killed_mid_round_reruns_to_every_seed_once(store):
    """A round's seeds as one population job (as on a GPU), the driver killed -9 while its
    members train: the rerun continues each member from its last checkpoint as its seed's own
    job, and the study ends with every seed FINISHED once."""
    args = study(
        store,
        *OBVIOUS_TD3,
        "hydra.sweeper.seeds_as_population=true",
        "hydra/launcher=basic",  # one population in flight when the driver dies
        "total_steps=2000",
        "checkpoint_every=250",
        "eval_every=250",
        "progress=false",
    )
    proc = spawn_cli(args, cwd=store["path"], new_session=True)

    def checkpointed_members() -> int:  # members past their second checkpoint, far from done
        marks = [r.data.tags.get(LOGGED_THROUGH_TAG) for r in job_runs(store)]
        return sum(mark is not None and 500 <= int(mark) < 1500 for mark in marks)

    try:
        deadline = time.monotonic() + 240
        while checkpointed_members() < 5:
            assert proc.poll() is None, proc.communicate()[0][-3000:]
            assert time.monotonic() < deadline
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.communicate()
    killed = {r.data.tags["walkers.job_key"] for r in job_runs(store) if r.info.status == "RUNNING"}
    assert len(killed) == 5, killed  # the population's five members, each under its own key

    result = run_cli(args, cwd=store["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    said = result.stdout + result.stderr
    runs = job_runs(store)
    finished = [r.data.tags["walkers.job_key"] for r in runs if r.info.status == "FINISHED"]
    assert len(finished) == len(set(finished)) == 10, finished  # every seed once, none twice
    assert killed <= set(finished)
    assert said.count("continuing it from its last checkpoint") == 5
    assert study_run(store).info.status == "FINISHED"


def test_a_terminated_study_ends_everything_it_started_and_reruns_to_its_answer(store):
    args = study(store, *OBVIOUS, "total_steps=2000", "checkpoint_every=500", "eval_every=500")
    proc = spawn_cli(args, cwd=store["path"], new_session=True)
    try:
        wait_for_a_job(store, proc, "FINISHED")
        os.killpg(proc.pid, signal.SIGTERM)  # `kill -TERM -<pgid>`, scancel, timeout
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr[-3000:]
    assert "interrupted: study 't' stopped" in stderr and "Traceback" not in stderr, stderr[-3000:]
    statuses = collections.Counter(r.info.status for r in all_runs(store["client"]))
    # the study, and a job if one ran
    assert set(statuses) <= {"FINISHED", "KILLED"}, (statuses, stderr[-3000:])
    assert study_run(store).info.status == "KILLED"

    again = run_cli(args, cwd=store["path"])
    assert again.returncode == 0, again.stderr[-3000:]
    assert study_run(store).info.status == "FINISHED"
    finished = [r for r in job_runs(store) if r.info.status == "FINISHED"]
    assert len(finished) == 10


def test_a_study_killed_on_one_machine_finishes_on_another_from_its_bundle(store, tmp_path):
    """The GPU box's case: a study killed -9 on one store (a machine given back mid-study) is
    exported with its checkpoints and imported into another store, where the same command
    finishes it: no finished seed runs again, and the job cut mid-run continues its own
    (imported) run from its checkpoint."""
    from tests.conftest import new_store

    args = ["total_steps=10000", "checkpoint_every=1000", "eval_every=1000", "progress=false"]
    proc = spawn_cli(study(store, *OBVIOUS, *args), cwd=store["path"], new_session=True)
    try:
        wait_for_a_job(store, proc, "FINISHED")
        wait_for_a_job(store, proc, "RUNNING", logged_below=5000)
        time.sleep(1.0)  # past its first checkpoint
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.communicate()
    before = {r.data.tags["walkers.job_key"]: r for r in job_runs(store)}
    finished_there = {k for k, r in before.items() if r.info.status == "FINISHED"}
    cut = {k for k, r in before.items() if r.info.status == "RUNNING"}
    assert finished_there and cut, {k: r.info.status for k, r in before.items()}

    bundle = tmp_path / "bundle"
    every = "statuses=[FINISHED,RUNNING,KILLED,FAILED]"
    done = export(store, "study=t", every, "checkpoints=true", f"out={bundle}")
    assert done.returncode == 0, done.stderr[-2000:]
    (tmp_path / "home").mkdir()
    home = new_store(tmp_path / "home")
    assert ingest(home, bundle).returncode == 0
    imported = {r.data.tags["walkers.job_key"]: r.info.run_id for r in job_runs(home)}

    result = run_cli(study(home, *OBVIOUS, *args), cwd=home["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    runs = job_runs(home)
    finished = [r.data.tags["walkers.job_key"] for r in runs if r.info.status == "FINISHED"]
    assert len(finished) == len(set(finished)) == 10, finished
    by_key = {r.data.tags["walkers.job_key"]: r for r in runs if r.info.status == "FINISHED"}
    for key in finished_there:  # not run again: the imported run is the one that counts
        assert by_key[key].info.run_id == imported[key]
    continued = [k for k in cut if by_key[k].info.run_id == imported[k]]
    assert continued, "the cut job started anew instead of continuing its imported run"
    assert "continuing it from its last checkpoint" in result.stdout + result.stderr
