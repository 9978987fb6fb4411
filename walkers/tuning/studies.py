"""A study's storage shared by several sweeper processes and a cluster's workers.

- :func:`open_storage`: Optuna's RDB storage (sqlite or PostgreSQL) with heartbeats: every
  sweeper records a heartbeat for each trial it runs (:class:`Heartbeats`); a trial whose sweeper
  died stops beating, and after ``grace_period`` the next sweeper on the study fails it and
  retries it once more (Optuna's ``RetryHeartbeatStaleTrialCallback``).
- :func:`study_lock`: "count the trials, then ask for more" as one step across processes, so
  that sweepers running one study together stop at exactly ``n_trials`` (Optuna's own
  ``MaxTrialsCallback`` races there). A PostgreSQL advisory lock; a file lock beside a sqlite file.
- :func:`counted_trials`: what ``n_trials`` counts: every trial but a failed one that was retried.
- :func:`job_storage`: how a job is told the storage: a URL that carries a password never
  travels by value (Hydra writes every job override to disk and prints it), only as a
  reference to the environment variable that holds it.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import re
import threading
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

import optuna
from optuna.exceptions import StorageInternalError
from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback
from optuna.trial import FrozenTrial, TrialState
from sqlalchemy.exc import OperationalError

from walkers.errors import ConfigError
from walkers.secrets import has_password, redacted
from walkers.tuning import optuna_internals

log = logging.getLogger("walkers")

UID_ATTR = "walkers.study_uid"
#: The environment variable that holds a shared storage's URL (``optuna=postgres`` reads it).
#: On a cluster, every node has it in its environment (exported before ``ray start``).
STORAGE_ENV = "WALKERS_OPTUNA_STORAGE"
#: What a study may be called: it goes into overrides, MLflow queries, run names and paths.
STUDY_NAME_CHARS = re.compile(r"[A-Za-z0-9_.:+@/ -]+")


def absolute_storage(storage: str | None) -> str | None:
    """``sqlite:///rel.db`` -> an absolute path, so every job finds the same file."""
    if storage and storage.startswith("sqlite:///") and not storage.startswith("sqlite:////"):
        return f"sqlite:///{Path(storage.removeprefix('sqlite:///')).resolve()}"
    return storage


def open_storage(
    url: str, heartbeat_interval: int | None, grace_period: int | None, max_retry: int | None
) -> RDBStorage:
    """The RDB storage at ``url``; a bad URL, an unreachable server or a refused login is a
    :class:`ConfigError` naming it (nothing is created)."""
    retry = RetryHeartbeatStaleTrialCallback(max_retry=max_retry) if heartbeat_interval else None
    try:
        return RDBStorage(
            url,
            # a connection the database dropped (it restarted) is replaced, not used and failed
            engine_kwargs={"pool_pre_ping": True},
            heartbeat_interval=heartbeat_interval or None,
            grace_period=grace_period if heartbeat_interval else None,
            heartbeat_stale_trial_callback=retry,
        )
    except Exception as e:
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(
            f"hydra.sweeper.storage={redacted(url)!r} cannot be used ({type(e).__name__}: "
            f"{reason}); "
            "give an Optuna RDB URL that works: sqlite:///<file>.db or "
            "postgresql+psycopg://<user>:<password>@<host>/<database> (optuna=postgres reads "
            "WALKERS_OPTUNA_STORAGE)"
        ) from None


def check_passed_by_reference(url: str | None) -> None:
    """A storage URL with a password must come from :data:`STORAGE_ENV`: given on the command
    line or in a yaml file it would be written to every job's ``.hydra/*.yaml`` and printed."""
    if has_password(url) and os.environ.get(STORAGE_ENV) != url:
        raise ConfigError(
            f"hydra.sweeper.storage={redacted(url)!r} carries a password, given by value: Hydra "
            "would write it into every job's .hydra/ files and print it; pass it by reference: "
            f"export {STORAGE_ENV}='<url>' and use optuna=postgres"
        )


def job_storage(url: str | None) -> str | None:
    """The storage as a job's ``trial.storage`` override value: a URL without secrets as it is
    (quoted), one with a password as a reference to :data:`STORAGE_ENV`, which the job resolves
    from its own environment (Ray workers inherit their node's)."""
    if url is None:
        return None
    if has_password(url):
        check_passed_by_reference(url)
        return hydra_quoted(f"${{oc.env:{STORAGE_ENV}}}")
    return hydra_quoted(url)


def hydra_quoted(value: str) -> str:
    """``value`` as a single-quoted Hydra override value that parses back to ``value``.

    Hydra's grammar: inside quotes a backslash escapes only a quote (or the backslashes just
    before one, or at the end); ``${`` would start an interpolation in a value of ours.
    """
    if "${" in value and not value.startswith("${oc.env:"):
        raise ConfigError(f"{value!r} is not allowed in an override value: it contains '${{'")
    escaped = re.sub(r"(\\*)'", lambda m: m.group(1) * 2 + "\\'", value)
    escaped = re.sub(r"(\\+)$", lambda m: m.group(1) * 2, escaped)
    return f"'{escaped}'"


def check_study_name(name: str) -> None:
    """A study name that travels safely through overrides, MLflow queries and file names."""
    if not STUDY_NAME_CHARS.fullmatch(name):
        raise ConfigError(
            f"hydra.sweeper.study_name={name!r} is not allowed: use letters, digits, spaces "
            "and _ . : + @ / - (no quotes)"
        )


def study_uid(study: optuna.Study) -> str:
    """A study's own id, made once (a study user attribute): a study deleted and created again
    under its name numbers its trials from 0 again, and must not match the old one's runs."""
    uid = study.user_attrs.get(UID_ATTR)
    if uid is None:
        uid = uuid.uuid4().hex[:12]
        study.set_user_attr(UID_ATTR, uid)
    return uid


def counted_trials(trials: list[FrozenTrial]) -> list[FrozenTrial]:
    """The trials ``n_trials`` counts: all of them but the failed ones that were retried (their
    retry, a new trial with the same parameters, counts instead)."""
    retried = {n for t in trials for n in RetryHeartbeatStaleTrialCallback.retry_history(t)}
    return [t for t in trials if t.number not in retried]


def original_number(trial: FrozenTrial) -> int:
    """The number of the trial a retry repeats (its own number if it is not a retry)."""
    original = RetryHeartbeatStaleTrialCallback.retried_trial_number(trial)
    return trial.number if original is None else original


@contextmanager
def study_lock(storage: RDBStorage, study_name: str):
    """Hold the study against other sweeper processes (PostgreSQL advisory lock, or an exclusive
    file lock for a sqlite file); other databases run unlocked."""
    url = storage.engine.url
    if url.get_backend_name() == "postgresql":
        key = int.from_bytes(hashlib.sha256(study_name.encode()).digest()[:8], "big", signed=True)
        with storage.engine.connect() as connection:
            connection.exec_driver_sql(f"SELECT pg_advisory_lock({key})")
            try:
                yield
            finally:
                connection.exec_driver_sql(f"SELECT pg_advisory_unlock({key})")
    elif url.get_backend_name() == "sqlite" and url.database not in (None, "", ":memory:"):
        with open(Path(url.database).with_suffix(".lock"), "a") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)
    else:
        yield


#: How long a sweeper waits for its study's database to come back (a restart) before giving up.
STORE_PATIENCE_S = float(os.environ.get("WALKERS_STORE_PATIENCE_S", 120))


def patiently(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``, tried again while the study's database cannot be reached (it
    restarts), for up to :data:`STORE_PATIENCE_S` seconds; other errors are raised at once."""
    deadline = time.monotonic() + STORE_PATIENCE_S
    while True:
        try:
            return fn(*args, **kwargs)
        except (OperationalError, StorageInternalError) as e:  # Optuna wraps some
            if time.monotonic() >= deadline:
                raise
            log.warning("the study's database is unreachable, trying again: %s",
                        str(e).splitlines()[0])  # fmt: skip
            time.sleep(3)


class Heartbeats:
    """A daemon thread recording a heartbeat every ``interval`` seconds for each trial this
    sweeper runs (:meth:`add` when asked, :meth:`remove` when told)."""

    def __init__(self, storage: RDBStorage, interval: int | None):
        self.storage, self.interval = storage, interval
        self._trials: set[int] = set()
        self._seen: set[int] = set()  # running trials whose clock this sweeper has started
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="optuna-heartbeats", daemon=True)

    def __enter__(self) -> Heartbeats:
        if self.interval:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def add(self, trial_id: int) -> None:
        if self.interval:
            self.storage.record_heartbeat(trial_id)  # at once: a trial never beaten is never stale
            self._seen.add(trial_id)
            with self._lock:
                self._trials.add(trial_id)

    def start_clocks(self, running: list[FrozenTrial]) -> None:
        """One heartbeat, once, for each running trial first seen here: Optuna never counts a
        trial without any heartbeat as stale, so one whose sweeper died before it recorded one
        (or a study from before heartbeats) would otherwise wait forever. A live sweeper's
        trials keep beating and stay fresh."""
        if not self.interval:
            return
        for trial in running:
            key = optuna_internals.trial_id(trial)
            if key not in self._seen:
                self._seen.add(key)
                self.storage.record_heartbeat(key)

    def remove(self, trial_id: int) -> None:
        with self._lock:
            self._trials.discard(trial_id)

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            with self._lock:
                trials = list(self._trials)
            for trial_id in trials:
                try:
                    self.storage.record_heartbeat(trial_id)
                except Exception:  # a database blip: the next beat retries
                    pass


def running(study: optuna.Study) -> list[FrozenTrial]:
    """Trials running, here or in another sweeper (possibly a dead one, until its heartbeats
    are overdue)."""
    return study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
