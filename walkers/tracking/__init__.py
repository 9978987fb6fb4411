"""Everything walkers does with MLflow, behind one face: the client side
(:mod:`~walkers.tracking.client`: connecting, queries, filters), a run's own
(:mod:`~walkers.tracking.tracker`: :class:`Tracker`, :func:`ending`) and the names of statuses,
tags and axes (:mod:`~walkers.tracking.names`, which imports no MLflow). Nothing happens at
import: each name is imported from its module when first used. The Hydra callbacks
(:mod:`~walkers.tracking.hydra_callbacks`) and the servers a team runs
(:mod:`~walkers.tracking.servers`) live beside them.
"""

from importlib import import_module

#: Where each name of the face lives; resolved on first use (PEP 562), so importing
#: ``walkers.tracking.names`` (or this face) imports no MLflow.
_HOMES = {
    "walkers.tracking.client": (
        "QUICK_HTTP_RETRIES",
        "connect",
        "download_checkpoint",
        "flatten",
        "get_or_create_experiment",
        "metric_history",
        "quoted",
        "require_run",
        "search_runs",
        "tags_equal",
        "ui_url",
    ),
    "walkers.secrets": ("redacted_uri",),  # imports no MLflow either
    "walkers.tracking.names": (
        "ABSENT",
        "BUDGET_TAG",
        "END_REASON_TAG",
        "ENV_STEPS",
        "FAILED",
        "FINISHED",
        "GRADIENT_STEPS",
        "JOB_KEY_TAG",
        "KILLED",
        "KIND_TAG",
        "LOGGED_THROUGH_TAG",
        "MULTIRUN_JOB_TAG",
        "ORIGIN_TAG",
        "PRUNED_TAG",
        "STUDY_KIND",
        "STUDY_TAG",
        "X_AXIS_TAG",
        "differing_keys",
        "status_after",
        "study_job_key",
        "study_jobs_prefix",
        "study_of_job_key",
        "total_steps_of",
    ),
    "walkers.tracking.tracker": (
        "STORE_PATIENCE_S",
        "Tracker",
        "end_running",
        "ending",
        "side_run",
    ),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}


def __getattr__(name: str):
    if name not in _HOME_OF:
        raise AttributeError(f"module 'walkers.tracking' has no attribute {name!r}")
    value = getattr(import_module(_HOME_OF[name]), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = sorted(_HOME_OF)
