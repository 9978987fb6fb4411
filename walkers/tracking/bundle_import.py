"""A results bundle put into a store, whole and once (:mod:`walkers.tracking.bundles` says how
an import is keyed, and what it refuses)."""

from __future__ import annotations

import contextlib
import json
import logging
import tempfile
from collections.abc import Iterable
from pathlib import Path

from mlflow.entities import Param, RunTag

from walkers.errors import ConfigError
from walkers.tracking.bundle_format import (
    ARTIFACTS_DIR,
    BATCH,
    CONFIG_ARTIFACT,
    FINGERPRINT_TAG,
    IMPORTED_FROM_TAG,
    IMPORTED_THROUGH_TAG,
    IMPORTING_TAG,
    Imported,
    metrics_of,
    origin_of,
    read_bundle,
)
from walkers.tracking.client import (
    get_or_create_experiment,
    search_runs,
    tags_equal,
)
from walkers.tracking.names import (
    FINISHED,
    JOB_KEY_TAG,
    KILLED,
    LOGGED_THROUGH_TAG,
    ORIGIN_TAG,
)

log = logging.getLogger("walkers")


# --- import -----------------------------------------------------------------------------------
def import_bundle(client, bundle: Path, experiment: str | None = None) -> Imported:
    """Put a bundle's runs into ``experiment`` (default: the one they were exported from) of the
    store ``client`` talks to. Checked whole before anything is written; each run is written
    whole or deleted (a stop between runs leaves whole runs, which the next import skips).

    A run already there is skipped, unless it is an earlier import of it, not trained on here,
    that the bundle has a later version of (the run went on where it came from: FINISHED since,
    or logged further): that copy is replaced. A copy trained on here that the bundle also went
    on with is a conflict: two continuations of one run."""
    document = read_bundle(bundle)
    experiment = experiment or document["source"]["experiment"]
    there = client.get_experiment_by_name(experiment)
    if there is not None:
        _delete_interrupted_imports(client, there.experiment_id)
    existing = search_runs(client, there.experiment_id) if there is not None else []
    by_origin = {origin_of(run): run for run in existing}
    finished_by_key = {
        run.data.tags[JOB_KEY_TAG]: run
        for run in existing
        if run.info.status == FINISHED and JOB_KEY_TAG in run.data.tags
    }
    todo, replaced = [], {}
    for record in document["runs"]:
        copy = by_origin.get(record["origin"])
        if copy is None:
            todo.append(record)
        elif _later_version(record, copy, bundle):
            todo.append(record)
            replaced[record["origin"]] = copy.info.run_id
    for record in todo:
        key = record["tags"].get(JOB_KEY_TAG)
        conflict = finished_by_key.get(key) if key else None
        if conflict is not None:
            raise ConfigError(
                f"bundle={str(bundle)!r}: run {record['origin']} ({key}) conflicts with run "
                f"{conflict.info.run_id} already FINISHED in experiment {experiment!r} under the "
                "same job key: nothing imported (import into another experiment: into=NAME)"
            )
    experiment_id = get_or_create_experiment(client, experiment)  # checked: now it may write
    # parents first, so that a job's run nests under its study's (or sweep's) imported run
    origins = {record["origin"] for record in todo}
    todo.sort(key=lambda r: r["tags"].get("mlflow.parentRunId") in origins)
    ids = {origin: run.info.run_id for origin, run in by_origin.items()}
    added = []
    for record in todo:
        run_id = _import_run(client, experiment_id, record, ids, document,
                             replacing=replaced.get(record["origin"]))  # fmt: skip
        ids[record["origin"]] = run_id
        added.append(run_id)
        if record["origin"] in replaced:  # its runs already here nest under the new copy
            for child in existing:
                if child.data.tags.get("mlflow.parentRunId") == replaced[record["origin"]]:
                    client.set_tag(child.info.run_id, "mlflow.parentRunId", run_id)
    present = len(document["runs"]) - len(todo)
    return Imported(experiment_id, added, present, updated=len(replaced))


def _later_version(record: dict, copy, bundle: Path) -> bool:
    """Whether ``record`` is a later state of ``copy`` (the store's run of the same origin) that
    should replace it; raises where both went on from the state they shared."""
    tags = copy.data.tags
    if ORIGIN_TAG not in tags or copy.info.status == FINISHED:
        return False  # the run itself (a bundle gone home), or a copy that is done
    arrived = tags.get(IMPORTED_THROUGH_TAG)
    mark = record["tags"].get(LOGGED_THROUGH_TAG)
    went_on = record["status"] == FINISHED or _steps(mark) > _steps(tags.get(LOGGED_THROUGH_TAG))
    if not went_on:
        return False  # the same state again, or an older one
    if arrived is None:  # imported before copies recorded it: whether it was trained on here
        log.warning(  # cannot be told, so it is kept
            "run %s (copy of %s) kept: the bundle holds a later version of it, but this copy "
            "predates the mark that tells whether it was trained on here (delete it in the UI, "
            "then import again, to take the bundle's)",
            copy.info.run_id,
            record["origin"],
        )
        return False
    if copy.info.status == "RUNNING" or arrived != tags.get(LOGGED_THROUGH_TAG, ""):
        raise ConfigError(
            f"bundle={str(bundle)!r}: run {record['origin']} went on where it came from "
            f"({record['status']}, logged through {mark}), and its copy {copy.info.run_id} here "
            f"was trained on too (logged through {tags.get(LOGGED_THROUGH_TAG)}): two "
            "continuations of one run; nothing imported (import into another experiment: "
            "into=NAME)"
        )
    return True


def _steps(mark: str | None) -> int:
    return int(mark) if mark else -1


def _delete_interrupted_imports(client, experiment_id: str) -> None:
    for run in search_runs(client, experiment_id, tags_equal({IMPORTING_TAG: "true"})):
        log.warning("deleting run %s: its import was interrupted", run.info.run_id)
        client.delete_run(run.info.run_id)


def _import_run(
    client, experiment_id: str, record: dict, by_origin: dict, document, replacing: str | None
) -> str:
    """One run, written whole under the importing tag; ``replacing``: the earlier copy it
    replaces, deleted before the run is done (a stop in between: the next import finds the
    new run unfinished and the old one gone, and imports it again)."""
    tags = dict(record["tags"])
    parent = tags.get("mlflow.parentRunId")
    if parent is not None:
        if parent in by_origin:
            tags["mlflow.parentRunId"] = by_origin[parent]
        else:  # its parent did not travel: a flat run rather than a dangling link
            del tags["mlflow.parentRunId"]
    tags |= {
        ORIGIN_TAG: record["origin"],
        IMPORTED_FROM_TAG: Path(document["root"]).name,
        IMPORTED_THROUGH_TAG: record["tags"].get(LOGGED_THROUGH_TAG, ""),
    }
    if record.get("fingerprint"):
        tags[FINGERPRINT_TAG] = json.dumps(record["fingerprint"])
    run = client.create_run(
        experiment_id,
        start_time=record["start_time"],
        tags={IMPORTING_TAG: "true"},
        run_name=record["run_name"],
    )
    run_id = run.info.run_id
    try:
        params = [Param(k, v) for k, v in record["params"].items()]
        for chunk in _chunks(params, BATCH["params"]):
            client.log_batch(run_id, params=chunk)
        for chunk in _chunks(list(metrics_of(record)), BATCH["metrics"]):
            client.log_batch(run_id, metrics=chunk)
        if record.get("config") is not None:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / CONFIG_ARTIFACT
                path.write_text(record["config"])
                client.log_artifact(run_id, str(path))
        root = Path(document["root"]) / ARTIFACTS_DIR / record["origin"]
        for artifact in record.get("artifacts", []):
            name = Path(artifact["path"])
            client.log_artifact(run_id, str(root / name), str(name.parent))
        tag_list = [RunTag(k, v) for k, v in tags.items()]
        for chunk in _chunks(tag_list, BATCH["tags"]):
            client.log_batch(run_id, tags=chunk)
        if replacing is not None:
            client.delete_run(replacing)
        # a run that was RUNNING where it came from is not running here: KILLED, so that its
        # job continues it from its checkpoint (or starts it anew without one)
        status = record["status"] if record["status"] != "RUNNING" else KILLED
        client.set_terminated(run_id, status, end_time=record["end_time"])
        client.delete_tag(run_id, IMPORTING_TAG)  # last: until then the next import redoes it
    except BaseException:
        with contextlib.suppress(Exception):
            client.delete_run(run_id)
        raise
    return run_id


def _chunks(items: list, size: int) -> Iterable[list]:
    for i in range(0, len(items), size):
        yield items[i : i + size]
