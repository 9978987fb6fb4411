"""Everything walkers does with MLflow, behind one face: the client side
(:mod:`~walkers.tracking.client`: connecting, queries, filters), a run's own
(:mod:`~walkers.tracking.tracker`: :class:`Tracker`, :func:`ending`) and the names of statuses,
tags and axes (:mod:`~walkers.tracking.names`, which imports no MLflow). Nothing happens at
import. The Hydra callbacks (:mod:`~walkers.tracking.hydra_callbacks`) and the servers a team
runs (:mod:`~walkers.tracking.servers`) live beside them.
"""

from walkers.tracking.client import (
    QUICK_HTTP_RETRIES,
    connect,
    download_checkpoint,
    flatten,
    get_or_create_experiment,
    metric_history,
    quoted,
    redacted_uri,
    require_run,
    search_runs,
    tags_equal,
    ui_url,
)
from walkers.tracking.names import (
    END_REASON_TAG,
    ENV_STEPS,
    FAILED,
    FINISHED,
    GRADIENT_STEPS,
    JOB_KEY_TAG,
    KILLED,
    KIND_TAG,
    LOGGED_THROUGH_TAG,
    PRUNED_TAG,
    X_AXIS_TAG,
)
from walkers.tracking.tracker import (
    STORE_PATIENCE_S,
    Tracker,
    end_running,
    ending,
    side_run,
)

__all__ = [
    "END_REASON_TAG",
    "ENV_STEPS",
    "FAILED",
    "FINISHED",
    "GRADIENT_STEPS",
    "JOB_KEY_TAG",
    "KILLED",
    "KIND_TAG",
    "LOGGED_THROUGH_TAG",
    "PRUNED_TAG",
    "QUICK_HTTP_RETRIES",
    "STORE_PATIENCE_S",
    "Tracker",
    "X_AXIS_TAG",
    "connect",
    "download_checkpoint",
    "end_running",
    "ending",
    "flatten",
    "get_or_create_experiment",
    "metric_history",
    "quoted",
    "redacted_uri",
    "require_run",
    "search_runs",
    "side_run",
    "tags_equal",
    "ui_url",
]
