"""The MLflow client side: connecting to a store (a server probed first, passwords refused),
experiments, queries, filters and the small helpers every command shares.

MLflow's HTTP client would retry a refused request with backoff for minutes; :func:`connect`
sets quicker defaults (a few retries, then the metrics wait for the next flush) when it is
called, never at import.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import time
import urllib.request
from collections.abc import Mapping
from pathlib import Path

from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from walkers.errors import CheckpointError, ConfigError
from walkers.interrupts import shielded
from walkers.secrets import refuse_password

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


@contextlib.contextmanager
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
