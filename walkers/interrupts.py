"""Places a stop signal may not land in: a call to the tracking store, a read or a write, and a
training step (:mod:`walkers.training.loops`: a stop inside an update left the checkpoint with
half an update).

walkers turns SIGINT and SIGTERM into a KeyboardInterrupt wherever the main thread is
(:func:`stop_cleanly_on_signals`, which walkers.train calls; a training started from Python gets
the same for SIGINT while it trains, :func:`stops_between_steps`), so a run ends KILLED after a
last checkpoint. Raised inside an MLflow call
to a sqlite store, a read as much as a write, that exception can leave the store's lock held by a
connection SQLAlchemy abandons: every later write, the run's last metrics and its KILLED status
included, then waits out sqlite's busy timeout and the run's store patience (seen under load: a
SIGTERM'd run still ending 3 minutes later; a study's KILLED writes failing "database is
locked"). Inside :func:`shielded` the signal is only noted; it is raised as soon as the call is
over. :class:`walkers.tracking.client.StoreClient` shields every call it makes.

Nor may a stop be lost. The handler raises wherever the main thread is, and that can be a
finalizer or a weakref callback run by the garbage collector (SQLAlchemy's, under MLflow):
Python prints such a callback's exception ("Exception ignored in") and carries on, so the run
trained on, deaf to further signals, until a supervisor's SIGKILL (seen: a run stopped by
``timeout -s INT`` 11 s after its start). :func:`_keep_a_swallowed_stop`, Python's unraisable
hook while walkers' handler is installed, delivers such a stop again once the main thread has
left the callback: raised there, or at the end of the training step or store call under way.
(It once noted the stop for the next of those to raise, and a multirun's driver still importing
its modules has none ahead before its jobs, other processes, train to their end: CI's 1 s
deadline ended with a FINISHED run.)

A Hydra config composition is the third place: a KeyboardInterrupt raised inside OmegaConf while
it builds a node comes out as a ConfigCompositionException (OmegaConf wraps what its half-built
node raises next), so a sweep's driver stopped between two jobs ended 1 and FAILED instead of 130
and KILLED. :class:`ShieldedConfigLoader` composes shielded; walkers' sweepers hand it to their
launchers (:mod:`walkers.plugins`).
"""

from __future__ import annotations

import _thread
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

_depth = 0  # shielded blocks open in the main thread (signals are handled there only)
_noted: int | None = None  # the signal that arrived inside one, raised when the last one ends


def shielding() -> bool:
    """True inside a :func:`shielded` block of the main thread."""
    return _depth > 0


def note(signum: int) -> None:
    """Keep a stop that arrived inside a shielded block, for the block's end to raise."""
    global _noted
    _noted = _noted or signum


def stop_noted() -> bool:
    """Whether a stop arrived inside the shielded block under way (a loop that is not ours, such
    as SB3's ``learn``, asks this to end at its next step; the block's end then raises it)."""
    return _noted is not None


class StopSignal(KeyboardInterrupt):
    """The KeyboardInterrupt walkers raises for SIGINT and SIGTERM."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"signal {signum}")
        self.signum = signum


class RunsStopped(KeyboardInterrupt):
    """A stop that ended runs: its message says which, and how they continue (the command's
    last line)."""


@contextmanager
def shielded() -> Iterator[None]:
    """Run the block to its end whatever stop signal arrives; then raise it (KeyboardInterrupt).

    In a thread other than the main one this does nothing: signals never interrupt those.
    """
    global _depth, _noted
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and _noted is not None:
            signum, _noted = _noted, None
            raise StopSignal(signum)


class ShieldedConfigLoader:
    """Hydra's config loader, whose compositions (a sweep's jobs', one by one) a stop signal
    waits for (:func:`shielded`); everything else is the loader's own. It pickles with its
    loader, as a cluster launcher sends it to its workers."""

    def __init__(self, loader) -> None:
        self.loader = loader

    def load_configuration(self, *args, **kwargs):
        with shielded():
            return self.loader.load_configuration(*args, **kwargs)

    def load_sweep_config(self, *args, **kwargs):
        with shielded():
            return self.loader.load_sweep_config(*args, **kwargs)

    def __getattr__(self, name: str):
        if name.startswith("__") or name == "loader":  # pickle's lookups before __dict__ is set
            raise AttributeError(name)
        return getattr(self.loader, name)


class _Stopping:
    """SIGINT and SIGTERM: the first one stops the run (a KeyboardInterrupt wherever the process
    is, once the training step or store call under way is over: :mod:`walkers.interrupts`; so
    every run ends KILLED after a last checkpoint); any further one while it ends is acknowledged
    in one line and otherwise ignored. ``timeout``, ``scancel`` or ``kill -TERM -<pgid>`` signal
    make and python both (make then forwards another), a supervisor may insist,
    a user may press Ctrl-C twice: none of these may break the checkpoint being written or leave
    the run RUNNING. ``kill -9`` still ends the process at once (``resume=`` continues from the
    last complete checkpoint)."""

    def __init__(self) -> None:
        self.stopping = self.told = False

    def __call__(self, signum, frame) -> None:
        if not self.stopping:
            self.stopping = True
            if shielding():  # inside a training step or a store call: raised after it
                note(signum)
                # a step can hold an evaluation, which can take a while: say why we wait
                name = signal.Signals(signum).name
                os.write(2, f"stopping ({name}): the step under way ends first\n".encode())
                return
            raise StopSignal(signum)
        if not self.told:  # os.write: print() may be in progress in the interrupted frame
            self.told = True
            name = signal.Signals(signum).name
            os.write(
                2,
                f"already stopping ({name} again): writing the last checkpoint and the runs' "
                "status first (kill -9 abandons them)\n".encode(),
            )


_STOPPING = _Stopping()


def _keep_a_swallowed_stop(unraisable) -> None:
    """Python's unraisable hook under walkers' handler: a stop raised inside a finalizer or a
    garbage-collection callback, which Python would print and drop, is delivered again once
    the main thread has left it; anything else goes to the hook there was before."""
    stop = unraisable.exc_value
    if not isinstance(stop, StopSignal):
        _hook_before(unraisable)
        return
    handler = signal.getsignal(stop.signum)
    if isinstance(handler, _Stopping):
        handler.stopping = False  # the signal again is the first one, not a second
    threading.Thread(target=_deliver_again, args=(stop.signum,), daemon=True).start()


def _deliver_again(signum: int) -> None:
    """The signal again, once the main thread has left the hook (a stop raised inside the hook
    would be dropped too)."""
    time.sleep(0.01)
    _thread.interrupt_main(signum)


_hook_before = sys.unraisablehook


def _keep_swallowed_stops() -> None:
    global _hook_before
    if sys.unraisablehook is not _keep_a_swallowed_stop:
        _hook_before = sys.unraisablehook
        sys.unraisablehook = _keep_a_swallowed_stop


def stop_cleanly_on_signals() -> None:
    """Ctrl-C and SIGTERM end this process as :class:`_Stopping` says, from now on (a multirun's
    driver and each job's worker process call it; a second call changes nothing)."""
    _keep_swallowed_stops()
    if signal.getsignal(signal.SIGTERM) is _STOPPING:
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _STOPPING)


@contextmanager
def stops_between_steps() -> Iterator[None]:
    """Inside, a Ctrl-C lands between the training steps, as under ``walkers.train`` (whose
    handler stays as it is): for a training started from Python, whose SIGINT would otherwise
    raise wherever the step is. The handler before is put back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGINT)
    if isinstance(before, _Stopping):
        yield
        return
    hook_before = sys.unraisablehook
    signal.signal(signal.SIGINT, _Stopping())
    _keep_swallowed_stops()
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
        sys.unraisablehook = hook_before
