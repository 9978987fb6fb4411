""" "Killed? the same command resumes" (README): a plain run's command, run again, continues the
run it started (a Ctrl-C, a SIGTERM, a kill -9), trains nothing once that run FINISHED, and
says which in one line; what identifies "the same command" is the composed config less what
may change on resume (:func:`walkers.training.command_plan.command_key`)."""

from __future__ import annotations

import logging
import re
import signal

import pytest

from tests.conftest import (
    TINY,
    all_runs,
    compose_cfg,
    metric_steps,
    one_line_error,
    run_cli,
    run_cli_signalled_after,
    spawn_cli,
    wait_for_uploaded_checkpoint,
)
from walkers.train import train
from walkers.training.command_plan import command_key
from walkers.training.provenance import CODE_DIGEST_TAG, COMMAND_KEY_TAG
from walkers.training.run import read_checkpoint

#: A run that takes long enough to be stopped after its first checkpoint.
RUN = [
    "env=pendulum",
    "seed=3",
    "total_steps=3000",
    "eval_every=500",
    "eval_episodes=1",
    "checkpoint_every=500",
    "algo.learning_starts=200",
    "algo.hidden_sizes=[16,16]",
    "progress=false",
]


def test_the_command_key_is_the_config_less_what_may_change_on_resume():
    key = command_key(compose_cfg(RUN))
    for same in (["total_steps=9000"], ["checkpoint_every=1000", "device=cpu"], ["work_dir=/x"]):
        assert command_key(compose_cfg([*RUN, *same])) == key, same
    for other in (["seed=4"], ["algo.lr=0.01"], ["tracking.run_name=again"], ["env=hopper"]):
        assert command_key(compose_cfg([*RUN, *other])) != key, other


@pytest.mark.faults  # `make test-faults`
@pytest.mark.parametrize("stop", [signal.SIGKILL, signal.SIGINT], ids=["kill-9", "ctrl-c"])
def test_the_same_command_continues_a_run_stopped_mid_way_to_its_budget(store, stop):
    args = [*RUN, *store["overrides"]]
    proc = spawn_cli(args, cwd=store["path"])
    try:
        wait_for_uploaded_checkpoint(proc, store["path"], "last.pt")
        proc.send_signal(stop)
        proc.communicate(timeout=180)
    finally:
        proc.kill()
    (run,) = all_runs(store["client"])
    run_id = run.info.run_id
    assert run.info.status == ("RUNNING" if stop == signal.SIGKILL else "KILLED")
    assert run.data.tags[COMMAND_KEY_TAG] == command_key(compose_cfg(args))

    again = run_cli(args, cwd=store["path"])
    assert again.returncode == 0, again.stderr[-2000:]
    said = again.stdout + again.stderr
    assert f"this command ran before as run(s) {run_id} ({run.info.status})" in said
    (run,) = all_runs(store["client"])  # that one run, continued to its budget
    assert run.info.run_id == run_id and run.info.status == "FINISHED"
    assert metric_steps(store["client"], run_id, "eval/return_mean") == [
        500, 1000, 1500, 2000, 2500, 3000
    ]  # each evaluation once  # fmt: skip
    path = store["client"].download_artifacts(run_id, "checkpoints/last.pt", str(store["path"]))
    assert read_checkpoint(path)["trainer"]["step"] == 3000

    third = run_cli(args, cwd=store["path"])
    assert third.returncode == 0, third.stderr[-2000:]
    assert f"this command already FINISHED as run(s) {run_id}: nothing to train" in (
        third.stdout + third.stderr
    )
    assert len(all_runs(store["client"])) == 1


def test_the_same_command_after_its_run_finished_trains_nothing_and_says_what_would(store, caplog):
    caplog.set_level(logging.INFO, logger="walkers")
    overrides = ["env=pendulum", "seed=5", "algo.learning_starts=200", *TINY, *store["overrides"]]
    value = train(compose_cfg(overrides))
    (run,) = all_runs(store["client"])
    caplog.clear()
    assert train(compose_cfg(["total_steps=1200", *overrides])) == value  # a larger budget too
    assert len(all_runs(store["client"])) == 1
    (line,) = [r.getMessage() for r in caplog.records if "already FINISHED" in r.getMessage()]
    assert f"resume={run.info.run_id} total_steps=<more>" in line, line
    assert "other update code" not in line

    # after the code changed, the same: its result stands, and the line says so
    store["client"].set_tag(run.info.run_id, CODE_DIGEST_TAG, "0" * 16)
    caplog.clear()
    assert train(compose_cfg(overrides)) == value
    (line,) = [r.getMessage() for r in caplog.records if "already FINISHED" in r.getMessage()]
    assert f"trained by other update code than this checkout's (run(s) {run.info.run_id})" in line

    # another name is another command: a new run of the same config
    train(compose_cfg([*overrides, "tracking.run_name=again"]))
    assert len(all_runs(store["client"])) == 2


def test_a_ctrl_c_before_any_run_exists_says_only_that(store):
    # SIGINT right after the first env is made: the agent and the run are not built yet
    result = run_cli_signalled_after(
        [*RUN, *store["overrides"]], store["path"], "gymnasium:make", calls=1
    )
    assert result.returncode == 130, result.stderr[-2000:]
    assert "interrupted: before a run started: nothing to continue" in result.stderr
    assert "KILLED" not in result.stdout + result.stderr and "Traceback" not in result.stderr
    assert all_runs(store["client"]) == []


def test_a_ctrl_c_of_a_run_says_which_run_it_ended(store):
    # SIGINT after the 50th Adam step: the run exists, and it ends KILLED with a checkpoint
    result = run_cli_signalled_after(
        [*RUN, *store["overrides"]], store["path"], "torch.optim:Adam.step", calls=50
    )
    assert result.returncode == 130, result.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
    assert (
        f"interrupted: MLflow run(s) {run.info.run_id} marked KILLED; the same command continues "
        "from the last checkpoint"
    ) in result.stderr


def test_the_same_command_continues_a_stopped_run_in_one_info_line_its_bar_where_it_was(store):
    """A run Ctrl-C'd at step 543, after its evaluation at 500, then its command again: the log
    says it continues in a routine INFO line (no warning), and the progress bar starts at the
    run's step with that evaluation's return, as the stopped session's bar ended."""
    args = [*RUN, "total_steps=700", "progress=true", *store["overrides"]]
    stopped = run_cli_signalled_after(
        args, store["path"], "walkers.training.bookkeeping:RunBook.after_step", calls=543
    )
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    (run,) = all_runs(store["client"])
    (evaluation,) = store["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    assert evaluation.step == 500
    shown = f"eval_return={evaluation.value:.1f}"
    assert "543/700" in _bar_lines(stopped.stderr)[-1]  # the step its checkpoint holds

    again = run_cli(args, cwd=store["path"])
    assert again.returncode == 0, again.stderr[-2000:]
    assert (
        f"[walkers][INFO] - this command ran before as run(s) {run.info.run_id} (KILLED): "
        "continuing it from its last checkpoint"
    ) in again.stdout
    assert "[walkers][WARNING]" not in again.stdout
    first, *_ = _bar_lines(again.stderr)
    assert re.search(rf"\b543/700 .*{re.escape(shown)}\]", first), first
    assert "700/700" in _bar_lines(again.stderr)[-1]


def _bar_lines(stderr: str) -> list[str]:
    """The progress bar's lines (tqdm redraws a line after a carriage return)."""
    return [line for line in re.split(r"[\r\n]", stderr) if "/700 [" in line]


@pytest.mark.faults  # `make test-faults`
def test_the_same_command_beside_its_run_in_training_is_refused_and_leaves_it_training(store):
    args = [*RUN, "total_steps=100000", *store["overrides"]]
    proc = spawn_cli(args, cwd=store["path"])
    try:
        wait_for_uploaded_checkpoint(proc, store["path"], "last.pt")
        (run,) = all_runs(store["client"])
        second = run_cli(args, cwd=store["path"])
        line = one_line_error(second)
        assert f"this command is training now as run {run.info.run_id} in another process" in line
        beside = run_cli([f"resume={run.info.run_id}", *store["overrides"]], cwd=store["path"])
        assert "a process of this machine is training the run" in one_line_error(beside)
        assert proc.poll() is None  # the first one trains on
        (run,) = all_runs(store["client"])
        assert run.info.status == "RUNNING"
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=180)
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
