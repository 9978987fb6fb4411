"""Places a stop signal may not land in: a call to the tracking store, a read or a write, and a
training step (:mod:`walkers.training.loops`: a stop inside an update left the checkpoint with
half an update).

walkers turns SIGINT and SIGTERM into a KeyboardInterrupt wherever the main thread is
(:mod:`walkers.cli`), so a run ends KILLED after a last checkpoint. Raised inside an MLflow call
to a sqlite store, a read as much as a write, that exception can leave the store's lock held by a
connection SQLAlchemy abandons: every later write, the run's last metrics and its KILLED status
included, then waits out sqlite's busy timeout and the run's store patience (seen under load: a
SIGTERM'd run still ending 3 minutes later; a study's KILLED writes failing "database is
locked"). Inside :func:`shielded` the signal is only noted; it is raised as soon as the call is
over. :class:`walkers.tracking.client.StoreClient` shields every call it makes.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

_depth = 0  # shielded blocks open in the main thread (signals are handled there only)
_noted: str | None = None  # the signal that arrived inside one, raised when the last one ends


def shielding() -> bool:
    """True inside a :func:`shielded` block of the main thread."""
    return _depth > 0


def note(reason: str) -> None:
    """Keep a stop that arrived inside a shielded block, for the block's end to raise."""
    global _noted
    _noted = _noted or reason


def stop_noted() -> bool:
    """Whether a stop arrived inside the shielded block under way (a loop that is not ours, such
    as SB3's ``learn``, asks this to end at its next step; the block's end then raises it)."""
    return _noted is not None


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
            reason, _noted = _noted, None
            raise KeyboardInterrupt(reason)
