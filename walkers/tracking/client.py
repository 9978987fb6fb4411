"""walkers' MLflow: connecting to a store (a server probed first, passwords refused), its
queries and filters, and a :class:`Tracker`, which owns one MLflow run: params, buffered metrics,
artifacts, its end.

MLflow's HTTP client would retry a refused request with backoff for minutes; :func:`connect`
sets quicker defaults (a few retries, then the metrics wait for the next flush) when it is
called, never at import.

Metrics are buffered and written in batches (a sqlite write per metric would cost more than a
TD3 update); the trainer flushes them after every evaluation and checkpoint, so a run's curves
move in the UI within one evaluation interval. Each flush records how far the run has logged
(tag ``walkers.logged_through``); a resumed run, which restarts from its last checkpoint, does
not log a metric again at or before the last step MLflow has of it, so no step is logged twice.
A store that fails mid-run does not stop training: unsent metrics are kept and retried at the
next flush, and written to a local file if they still can't be sent. :func:`ending` is the one
place a run's status is set.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import time
import urllib.request
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from mlflow.entities import Metric, Param, RunTag
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from walkers.errors import CheckpointError, ConfigError
from walkers.interrupts import shielded
from walkers.secrets import refuse_password
from walkers.tracking.names import END_REASON_TAG, FAILED, FINISHED, KILLED, LOGGED_THROUGH_TAG

log = logging.getLogger("walkers.tracking")

#: MLflow's INFO lines that say nothing a user acts on (a new sqlite store's schema, the system
#: metrics monitor starting and stopping, four lines a run): its warnings and errors still show.
for _chatty in ("mlflow.store.db.utils", "mlflow.system_metrics", "alembic"):
    logging.getLogger(_chatty).setLevel(logging.WARNING)

#: MLflow's HTTP retry settings for a tracking server that is down (restarting): a few quick
#: retries, then the metrics wait for the next flush (Tracker.flush keeps them). A user's own
#: settings of these variables win.
QUICK_HTTP_RETRIES = {
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2",
    "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "30",
}


#: What MLflow's UI reads an experiment's kind from: walkers' experiments are model training,
#: not GenAI applications (the tag alone did not switch the view in 3.17; the links below do).
EXPERIMENT_KIND_TAG, MODEL_TRAINING_KIND = "mlflow.experimentKind", "custom_model_development"
#: The query that opens MLflow's UI on its model-training view (checked in headless Chromium).
TRAINING_VIEW = "?workflowType=machine_learning"


def ui_url(experiment_id: str, run_id: str | None = None, host: str = "http://127.0.0.1:5000"):
    """Direct link to the training-runs table, or a run's page, in the model-training view
    (MLflow 3.17 opens an experiment as a GenAI application unless the URL asks for it)."""
    url = f"{host}/#/experiments/{experiment_id}/runs"
    return f"{url}/{run_id}{TRAINING_VIEW}" if run_id else f"{url}{TRAINING_VIEW}"


def _artifact_location(uri: str) -> str | None:
    """Keep a sqlite store's artifacts beside its database file (``mlartifacts/``)."""
    if uri.startswith("sqlite:///"):
        db = Path(uri.removeprefix("sqlite:///")).resolve()
        return (db.parent / "mlartifacts").as_uri()
    return None


class StoreClient(MlflowClient):
    """An :class:`MlflowClient` whose public calls, reads included, each run to their end
    whatever stop signal arrives; the signal is raised as soon as the call is over
    (:func:`walkers.interrupts.shielded`).

    A KeyboardInterrupt raised inside SQLAlchemy, in a read as much as in a write, can leave a
    connection holding the database's lock; every later write of the process, and of every other
    process on the same sqlite file, then waits out the busy timeout (seen in CI: a study's
    SIGTERM landing in a job's ``get_experiment_by_name``, and the study's own KILLED writes
    failing with "database is locked").
    """

    def __getattribute__(self, name: str):
        attribute = super().__getattribute__(name)
        if name.startswith("_") or not callable(attribute):
            return attribute

        @functools.wraps(attribute)
        def to_its_end(*args, **kwargs):
            with shielded():
                return attribute(*args, **kwargs)

        return to_its_end


def _with_retries(fn, *args, attempts: int = 8, **kwargs):
    """Call ``fn``, retrying sqlite's transient "database is locked" under parallel jobs (a
    :class:`StoreClient`'s call already holds a stop signal until it returns)."""
    for attempt in range(attempts):
        try:
            return fn(*args, **kwargs)
        except MlflowException as e:
            if "locked" not in str(e) or attempt == attempts - 1:
                raise
            time.sleep(0.2 * 2**attempt)


def get_or_create_experiment(client: MlflowClient, name: str) -> str:
    """Experiment id for ``name``, creating it (safely against a concurrent creator)."""
    experiment = _with_retries(client.get_experiment_by_name, name)
    if experiment is not None:
        return experiment.experiment_id
    try:
        return _with_retries(
            client.create_experiment,
            name,
            artifact_location=_artifact_location(client.tracking_uri),
            tags={EXPERIMENT_KIND_TAG: MODEL_TRAINING_KIND},
        )
    except MlflowException:
        experiment = client.get_experiment_by_name(name)
        if experiment is None:
            raise
        return experiment.experiment_id


def connect(uri: str, looking_for: str | None = None) -> StoreClient:
    """A :class:`StoreClient` for ``uri``; an unreachable or unusable store is a
    :class:`ConfigError`, and so is a sqlite file that does not exist when the command is
    ``looking_for`` something already in the store (``"resume='<id>'"``): connecting would
    create an empty store where nobody asked for one.

    A server is probed once, quickly, first: MLflow's own client retries a refused connection
    with backoff for minutes before it gives up.
    """
    for name, value in QUICK_HTTP_RETRIES.items():
        os.environ.setdefault(name, value)
    refuse_password(uri)
    db = Path(uri.removeprefix("sqlite:///"))
    if looking_for and uri.startswith("sqlite:///") and not db.exists():
        raise ConfigError(
            f"{looking_for} is not a run in tracking.uri={uri!r}: there is no store there "
            f"({db} does not exist); pass the tracking.uri the run was logged to"
        )
    try:
        if uri.startswith(("http://", "https://")):
            urllib.request.urlopen(f"{uri.rstrip('/')}/health", timeout=10).close()
        client = StoreClient(tracking_uri=uri)
        _with_retries(client.search_experiments, max_results=1)
    except Exception as e:
        raise ConfigError(
            f"tracking.uri={uri!r} cannot be used ({type(e).__name__}: {str(e).splitlines()[0]}); "
            "use sqlite:///<file>.db, http(s)://<server> or unset MLFLOW_TRACKING_URI"
        ) from None
    return client


def require_run(client: MlflowClient, run_id: str, uri: str, key: str = "run_id"):
    """The run ``run_id``; a :class:`ConfigError` naming ``key`` and the store if there is none."""
    try:
        return client.get_run(run_id)
    except Exception:
        raise ConfigError(
            f"{key}={run_id!r} is not a run in tracking.uri={uri!r}; pass the run id shown at "
            "the end of a training run or in the MLflow UI"
        ) from None


_PROGRESS_BAR = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"


@contextmanager
def no_progress_bars():
    """MLflow draws a progress bar on stderr for every artifact it downloads (three lines each
    for one small checkpoint): nothing a user acts on."""
    before = os.environ.get(_PROGRESS_BAR)
    os.environ[_PROGRESS_BAR] = "false"
    try:
        yield
    finally:
        if before is None:
            del os.environ[_PROGRESS_BAR]
        else:
            os.environ[_PROGRESS_BAR] = before


def download_checkpoint(client: MlflowClient, run_id: str, filename: str, dst) -> Path:
    """``checkpoints/<filename>`` of a run, downloaded into the folder ``dst``."""
    try:
        with no_progress_bars():
            return Path(client.download_artifacts(run_id, f"checkpoints/{filename}", str(dst)))
    except Exception:
        raise CheckpointError(f"run {run_id} has no checkpoints/{filename} artifact") from None


def quoted(value: str) -> str:
    """``value`` as a string literal of an MLflow filter, in whichever quote it does not
    contain (MLflow's filter grammar has no escapes)."""
    quote = "'" if "'" not in value else '"'
    if quote in value:
        raise ConfigError(f"{value!r} cannot be searched in MLflow: it has both quotes")
    return f"{quote}{value}{quote}"


def tags_equal(tags: Mapping[str, str]) -> str:
    """An MLflow filter string: every tag in ``tags`` equal to its value."""
    return " and ".join(f"tags.`{key}` = {quoted(str(value))}" for key, value in tags.items())


def search_runs(client: MlflowClient, experiment_id: str, filter_string: str = "") -> list:
    """Every run of an experiment matching ``filter_string`` (all pages)."""
    runs, token = [], None
    while True:
        page = client.search_runs(
            [experiment_id], filter_string, max_results=5000, page_token=token
        )
        runs.extend(page)
        token = page.token
        if not token:
            return runs


def metric_history(client: MlflowClient, run_id: str, key: str) -> tuple[list[int], list[float]]:
    """``(steps, values)`` of one metric, in step order."""
    history = sorted(client.get_metric_history(run_id, key), key=lambda m: m.step)
    return [m.step for m in history], [m.value for m in history]


def flatten(d: Mapping, prefix: str = "") -> dict[str, str]:
    """{"algo": {"lr": 3e-4}} -> {"algo.lr": "0.0003"} (lists stay whole: "[256, 256]")."""
    out = {}
    for key, value in d.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = str(value)
    return out


MLFLOW_MAX_PARAMS_PER_BATCH = 100
#: How long a run that ends waits for a store that is down (restarting) to take its last
#: metrics and its status, and how often it tries again.
STORE_PATIENCE_S = float(os.environ.get("WALKERS_STORE_PATIENCE_S", 120))
STORE_POLL_S = 3.0


def end_running(client: MlflowClient, experiment: str, query: str, status: str, reason: str):
    """End the runs of ``experiment`` matching ``query`` that are still RUNNING, with ``status``
    and ``reason`` (tag ``walkers.end_reason``): the runs of jobs that died with their driver,
    which cannot end them themselves. Returns their ids."""
    found = client.get_experiment_by_name(experiment)
    ended = []
    for run in search_runs(client, found.experiment_id, query) if found else []:
        if run.info.status == "RUNNING":
            tracker = Tracker.attach(client, run.info.run_id, ".")
            tracker.set_tags({END_REASON_TAG: reason[:500]})
            tracker.end(status)
            ended.append(run.info.run_id)
    return ended


@contextmanager
def _killed_if_stopped() -> Iterator[list[Tracker]]:
    """Open a run (create it, or set it RUNNING again) and append its :class:`Tracker` to the
    list this yields. A stop signal meanwhile waits for the block's end, and the run opened so
    far ends KILLED then: otherwise it would stay RUNNING with nothing left to end it."""
    made: list[Tracker] = []
    try:
        with shielded():
            yield made
    except KeyboardInterrupt:
        for tracker in made:
            tracker.end(KILLED)
        raise


@contextmanager
def ending(trackers: list[Tracker], shared: Callable[[], bool] | None = None):
    """Every run in ``trackers`` (a list that may grow inside the block) gets its final status
    on the way out: FINISHED, KILLED (Ctrl-C, or SIGTERM turned into it) or FAILED (anything
    else). The one place a run's status is set, for training runs, populations, sweeps and
    side runs alike.

    ``shared``: for a run that other processes share (a study's run, one per study however many
    sweepers run it): while it returns True on the way out, the runs are left RUNNING for the
    last process out to end.
    """
    status = FAILED
    try:
        yield
        status = FINISHED
    except KeyboardInterrupt:
        status = KILLED
        raise
    finally:
        if shared is not None and shared():
            for tracker in trackers:
                tracker.flush()
                log.info("run %s stays RUNNING: others still work on it", tracker.run_id)
        else:
            for tracker in trackers:
                tracker.end(status)


@contextmanager
def side_run(client: MlflowClient, experiment: str, run_name: str, tags: dict, spool_dir):
    """A run that records something other than training (a report, a dataset's stats)."""
    tracker = Tracker.start(client, experiment, run_name=run_name, tags=tags, spool_dir=spool_dir)
    with ending([tracker]):
        yield tracker


class Tracker:
    """One MLflow run: params, buffered metrics, artifacts, end status."""

    def __init__(
        self,
        client: MlflowClient,
        run_id: str,
        experiment_id: str,
        spool_dir: Path,
        logged_through: int | None = None,
    ):
        self.client, self.run_id, self.experiment_id = client, run_id, experiment_id
        self.spool_dir = Path(spool_dir)
        self._pending: list[Metric] = []
        self.status: str | None = None  # the final status, once end() has set it
        #: steps up to here were logged by an earlier attempt of this run: not logged again
        self.logged_through = logged_through
        self._sent_through = logged_through or 0  # the highest step sent so far
        self._logged: dict[str, int] = {}  # a resumed run: each metric's last step in MLflow
        self._monitor = None  # MLflow's system metrics sampler, once started

    @classmethod
    def start(cls, client, experiment: str, run_name: str, tags: dict, spool_dir) -> Tracker:
        experiment_id = get_or_create_experiment(client, experiment)
        with _killed_if_stopped() as made:
            run = _with_retries(client.create_run, experiment_id, run_name=run_name, tags=tags)
            made.append(cls(client, run.info.run_id, experiment_id, spool_dir))
        return made[0]

    @classmethod
    def reopen(cls, client, run_id: str, spool_dir, resumed_training: bool = False) -> Tracker:
        """The run ``run_id``, RUNNING again. ``resumed_training``: a training run continued
        from its last checkpoint, which logs nothing at or before its logged-through mark."""
        run = client.get_run(run_id)
        mark = run.data.tags.get(LOGGED_THROUGH_TAG) if resumed_training else None
        with _killed_if_stopped() as made:
            _with_retries(client.update_run, run_id, status="RUNNING")
            tracker = cls(client, run_id, run.info.experiment_id, spool_dir, mark and int(mark))
            made.append(tracker)
            if resumed_training:  # per metric: a step split over two requests, or final/* unsent
                tracker._logged = {
                    key: max(m.step for m in client.get_metric_history(run_id, key))
                    for key in run.data.metrics
                }
        return tracker

    def start_system_metrics(self, every_s: float) -> None:
        """Sample CPU, memory, disk, network (and GPU where present) into the run's "System
        metrics" tab every ``every_s`` seconds until :meth:`end` (MLflow's own monitor)."""
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        try:
            self._monitor = SystemMetricsMonitor(
                self.run_id,
                sampling_interval=every_s,
                resume_logging=bool(self._logged),
                tracking_uri=self.client.tracking_uri,
            )
            self._monitor.start()
        except Exception as e:  # a nice-to-have: never a reason to stop training
            log.warning("no system metrics for run %s: %s", self.run_id, e)
            self._monitor = None

    @classmethod
    def reopen_or_start(
        cls, client, experiment: str, query: str, run_name: str, tags: dict, spool_dir
    ) -> Tracker:
        """The first run of ``experiment`` matching ``query`` reopened (given ``tags``, which
        may have changed), or else a new run: a study's or a trial's run, continued by a resumed
        study or a retried trial."""
        experiment_id = get_or_create_experiment(client, experiment)
        for run in search_runs(client, experiment_id, query):
            tracker = cls.reopen(client, run.info.run_id, spool_dir)
            tracker.set_tags(tags)
            return tracker
        return cls.start(client, experiment, run_name=run_name, tags=tags, spool_dir=spool_dir)

    @classmethod
    def attach(cls, client, run_id: str, spool_dir) -> Tracker:
        """Log more to an existing run (e.g. evaluation videos) without changing its status."""
        return cls(client, run_id, client.get_run(run_id).info.experiment_id, spool_dir)

    @property
    def url(self) -> str:
        """The run in the MLflow UI: on the tracking server itself, else a local `make ui`."""
        server = self.client.tracking_uri
        if server.startswith(("http://", "https://")):
            return ui_url(self.experiment_id, self.run_id, host=server.rstrip("/"))
        return ui_url(self.experiment_id, self.run_id)

    def log_params(self, params: Mapping[str, str]) -> None:
        items = [Param(k, str(v)) for k, v in params.items()]
        for i in range(0, len(items), MLFLOW_MAX_PARAMS_PER_BATCH):
            chunk = items[i : i + MLFLOW_MAX_PARAMS_PER_BATCH]
            _with_retries(self.client.log_batch, self.run_id, params=chunk)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        _with_retries(
            self.client.log_batch, self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()]
        )

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        """Queue metrics at env step ``step``; they are written at the next :meth:`flush`."""
        now = int(time.time() * 1000)
        self._pending.extend(
            Metric(k, float(v), now, int(step))
            for k, v in metrics.items()
            if step > self._logged.get(k, -1)  # else an earlier attempt of the run logged it
        )

    def flush(self) -> bool:
        """Send queued metrics; on failure keep them for the next try. True if all were sent."""
        while self._pending:
            chunk = self._pending[:1000]
            # the mark travels in the same request as the metrics: a crash between them would
            # leave metrics beyond the mark, logged a second time by the resumed run
            self._sent_through = max(self._sent_through, *(m.step for m in chunk))
            mark = RunTag(LOGGED_THROUGH_TAG, str(self._sent_through))
            # a stop signal waits for the write and its bookkeeping (the retries included,
            # which the run's ending would wait for anyway): what was sent is never resent
            with shielded():
                try:
                    _with_retries(self.client.log_batch, self.run_id, metrics=chunk, tags=[mark])
                except Exception as e:
                    log.warning(
                        "MLflow unreachable, %d metrics kept for later: %s", len(self._pending), e
                    )
                    return False
                del self._pending[: len(chunk)]
        return True

    def log_artifact(self, path, artifact_path: str | None = None) -> bool:
        try:
            _with_retries(self.client.log_artifact, self.run_id, str(path), artifact_path)
            return True
        except Exception as e:
            log.warning("could not upload %s to MLflow (kept locally): %s", path, e)
            return False

    def end(self, status: str) -> None:
        """Flush and set the final status; metrics MLflow never took go to a local jsonl file."""
        if self._monitor is not None:
            try:
                self._monitor.finish()
            except Exception as e:
                log.warning("system metrics monitor of run %s: %s", self.run_id, e)
            self._monitor = None
        deadline = time.monotonic() + STORE_PATIENCE_S
        while not self.flush() and time.monotonic() < deadline:  # a store that restarts
            time.sleep(STORE_POLL_S)
        if self._pending:
            spool = self.spool_dir / "unlogged_metrics.jsonl"
            spool.parent.mkdir(parents=True, exist_ok=True)
            with spool.open("a") as f:
                for m in self._pending:
                    f.write(json.dumps({"key": m.key, "value": m.value, "step": m.step}) + "\n")
            log.error("%d metrics could not be logged; saved to %s", len(self._pending), spool)
        self.status = status
        while True:  # a run left RUNNING is a lie: wait a while for a store that restarts
            try:
                _with_retries(self.client.set_terminated, self.run_id, status)
                return
            except Exception as e:
                if time.monotonic() >= deadline:
                    log.error("could not set MLflow run %s to %s: %s", self.run_id, status, e)
                    return
                log.warning("MLflow unreachable: run %s ends %s once it is back", self.run_id,
                            status)  # fmt: skip
                time.sleep(STORE_POLL_S)
