"""A stop signal that arrives while a run reads or writes its store waits for the call's end.

Real signals to this process through walkers' own handler, a real sqlite MLflow store.
"""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest
import sqlalchemy
from mlflow.tracking import MlflowClient

from walkers import interrupts
from walkers.tracking.client import Tracker, connect


class _SignalledInsideWrites(MlflowClient):
    """A store client that gets SIGTERM at the start of every metrics write."""

    def log_batch(self, run_id, metrics=(), params=(), tags=(), **kwargs):
        if metrics:
            os.kill(os.getpid(), signal.SIGTERM)  # its handler runs inside the write below
        return super().log_batch(run_id, metrics=metrics, params=params, tags=tags, **kwargs)


class _SignalledWhileOpeningRuns(MlflowClient):
    """A store client that gets SIGTERM while it creates a run or sets one RUNNING again."""

    def create_run(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return super().create_run(*args, **kwargs)

    def update_run(self, run_id, status=None, **kwargs):
        if status == "RUNNING":
            os.kill(os.getpid(), signal.SIGTERM)
        return super().update_run(run_id, status=status, **kwargs)


@pytest.fixture
def stop_handler():
    """walkers' SIGINT/SIGTERM handler in this process, put back as it was afterwards."""
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    hook_before = sys.unraisablehook
    interrupts.stop_cleanly_on_signals()
    yield
    for sig, handler in before.items():
        signal.signal(sig, handler)
    sys.unraisablehook = hook_before
    interrupts._STOPPING.stopping = interrupts._STOPPING.told = False


def test_a_signal_inside_a_metrics_write_is_raised_after_it(store, tmp_path, stop_handler):
    client = _SignalledInsideWrites(store["uri"])
    tracker = Tracker.start(client, "shielded", "run", {}, tmp_path / "spool")
    tracker.log_metrics({"eval/return_mean": 1.5, "loss/critic": 0.25}, step=600)

    with pytest.raises(KeyboardInterrupt, match=f"signal {signal.SIGTERM}"):
        tracker.flush()

    assert not interrupts.shielding()
    assert tracker._pending == []  # written, so not sent a second time when the run ends
    other = MlflowClient(store["uri"])  # the store is not left locked: another writer gets in
    other.set_tag(tracker.run_id, "after", "the signal")
    run = other.get_run(tracker.run_id)
    assert run.data.metrics == {"eval/return_mean": 1.5, "loss/critic": 0.25}
    assert run.data.tags["after"] == "the signal"
    tracker.end("KILLED")
    assert other.get_run(tracker.run_id).info.status == "KILLED"


def test_shielded_blocks_nest_and_raise_once_at_the_outermost(stop_handler):
    with pytest.raises(KeyboardInterrupt):
        with interrupts.shielded():
            with interrupts.shielded():
                os.kill(os.getpid(), signal.SIGTERM)
                assert interrupts.shielding()
            reached_after_the_inner_block = True
    assert reached_after_the_inner_block
    assert not interrupts.shielding()


def test_a_signal_inside_a_read_is_raised_after_it_and_leaves_the_store_unlocked(
    store, stop_handler
):
    client = connect(store["uri"])
    engine = client._tracking_client.store.engine
    signalled = []

    def signal_inside_the_first_select(conn, cursor, statement, *args):
        if statement.lstrip().upper().startswith("SELECT") and not signalled:
            signalled.append(statement)
            os.kill(os.getpid(), signal.SIGTERM)  # its handler runs inside SQLAlchemy's read

    sqlalchemy.event.listen(engine, "before_cursor_execute", signal_inside_the_first_select)
    try:
        with pytest.raises(KeyboardInterrupt, match=f"signal {signal.SIGTERM}") as stopped:
            client.get_experiment_by_name("Default")
    finally:
        sqlalchemy.event.remove(engine, "before_cursor_execute", signal_inside_the_first_select)

    assert signalled
    assert stopped.traceback[-1].path.name == "interrupts.py"  # raised after the read, not in it
    assert not interrupts.shielding()
    other = MlflowClient(store["uri"])  # the store is not left locked: another writer gets in
    run = other.create_run(client.get_experiment_by_name("Default").experiment_id)
    other.set_terminated(run.info.run_id, "KILLED")
    assert client.get_run(run.info.run_id).info.status == "KILLED"


def test_a_signal_while_a_run_is_opened_ends_that_run_killed(store, tmp_path, stop_handler):
    client = _SignalledWhileOpeningRuns(store["uri"])
    with pytest.raises(KeyboardInterrupt, match=f"signal {signal.SIGTERM}"):
        Tracker.start(client, "opened", "run", {}, tmp_path / "spool")
    experiment = client.get_experiment_by_name("opened")
    (run,) = MlflowClient(store["uri"]).search_runs([experiment.experiment_id])
    assert run.info.status == "KILLED"  # not RUNNING with nothing left to end it

    interrupts._STOPPING.stopping = False  # a later process continues it, and is stopped in turn
    with pytest.raises(KeyboardInterrupt, match=f"signal {signal.SIGTERM}"):
        Tracker.reopen(client, run.info.run_id, tmp_path / "spool", resumed_training=True)
    assert MlflowClient(store["uri"]).get_run(run.info.run_id).info.status == "KILLED"


class _SignalledWhileCollected:
    """An object whose finalizer gets SIGTERM: its handler runs inside the finalizer, whose
    exceptions Python prints ("Exception ignored in") and drops, as a SQLAlchemy weakref
    callback run by the garbage collector did under MLflow."""

    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100_000):  # the handler runs here, at the latest
            pass


def test_a_signal_inside_a_finalizer_outside_any_step_or_store_call_still_stops(stop_handler):
    # e.g. a multirun's driver importing its modules: no block ahead would raise a noted stop
    # before its jobs, other processes, trained to their end
    with pytest.raises(KeyboardInterrupt, match=f"signal {signal.SIGTERM}"):
        _SignalledWhileCollected()
        for _ in range(500):
            time.sleep(0.01)
        pytest.fail("the stop was lost in the finalizer")
    assert not interrupts.stop_noted()
