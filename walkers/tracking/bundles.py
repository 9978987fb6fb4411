"""Results bundles: runs taken out of one MLflow store and put into another, whole and once.

A bundle is a folder::

    <bundle>/runs.json.gz        every run: params, tags, status, times, the full history of
                                 every metric (step, value, time), its composed config.yaml
    <bundle>/artifacts/<origin>/ checkpoints, when exported with them (sha256 in runs.json.gz)

``runs.json.gz`` describes itself: ``format`` and ``version`` say what reads it, ``source`` what
was selected from which experiment, and each run carries its provenance (the code's commit,
package versions, device, CPU-hours: tags, params and metrics the run logged itself).

Importing is keyed, as a study's reruns are. Every imported run is tagged with its origin
(``walkers.origin``: the run id in the store it was first logged to, kept through any number of
copies), so a bundle imported twice adds nothing. A run whose job key (``walkers.job_key``)
already has a FINISHED run of another origin in the target experiment is a conflict: the import
is refused before anything is written. FINISHED runs imported this way count as done for the
study that made them: the same study command on the target store runs only what is missing.

Why not mlflow-export-import (read first): it copies runs through the REST API into per-run
folders of JSON and every artifact (megabytes per run with models and videos), creates new runs
on every import (a second import duplicates the study's seeds), and knows no job keys; it would
also bring its own pins of MLflow. What walkers needs is a few hundred lines over MLflow's own
client: one compact file, keyed and idempotent imports, checked before writing.
"""

from __future__ import annotations

import gzip
import json
import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from mlflow.exceptions import MlflowException

from walkers.errors import ConfigError
from walkers.tracking import histories
from walkers.tracking.bundle_format import (
    ARTIFACTS_DIR,
    CHECKPOINTS,
    CONFIG_ARTIFACT,
    FINGERPRINT_TAG,
    FORMAT,
    IMPORTED_FROM_TAG,
    IMPORTING_TAG,
    ORIGIN_TAG,
    RUNS_FILE,
    VERSION,
    BundleRuns,
    Exported,
    Imported,
    origin_of,
    read_bundle,
    sha256_of,
)
from walkers.tracking.bundle_import import import_bundle
from walkers.tracking.client import (
    no_progress_bars,
    search_runs,
)
from walkers.tracking.names import (
    JOB_KEY_TAG,
    KIND_TAG,
    LOGGED_THROUGH_TAG,
    STUDY_KIND,
    STUDY_TAG,
    study_jobs_prefix,
)

#: What the bundle's users call (its format and import are modules of their own).
__all__ = [
    "FINGERPRINT_TAG",
    "IMPORTED_FROM_TAG",
    "IMPORTING_TAG",
    "ORIGIN_TAG",
    "RUNS_FILE",
    "BundleRuns",
    "Exported",
    "Imported",
    "export_runs",
    "import_bundle",
    "read_bundle",
    "runs_to_export",
]

log = logging.getLogger("walkers")


# --- export -----------------------------------------------------------------------------------
def runs_to_export(
    client, experiment_id: str, study: str | None, where: dict[str, str], statuses: list[str]
) -> list:
    """The runs to export: a study's (its own run and its jobs'), else the whole experiment;
    then those whose tags equal ``where`` (e.g. ``{algo: td3, env: Walker2d-v5}``) and whose
    status is in ``statuses`` (a study's own run is kept whatever its status).

    A study's jobs are the runs nested under its run and the runs keyed as its jobs: those it
    decided on without training them (imported from a bundle, or trained before its run began)
    nest elsewhere or nowhere."""
    runs = search_runs(client, experiment_id)
    if study is not None:
        own = [
            r
            for r in runs
            if r.data.tags.get(KIND_TAG) == STUDY_KIND and r.data.tags.get(STUDY_TAG) == study
        ]
        if not own:
            raise ConfigError(f"study={study!r} has no run in this experiment: nothing exported")
        ids, prefix = {r.info.run_id for r in own}, study_jobs_prefix(study)
        jobs = [
            r
            for r in runs
            if r.data.tags.get("mlflow.parentRunId") in ids
            or r.data.tags.get(JOB_KEY_TAG, "").startswith(prefix)
        ]
        runs = own + [r for r in jobs if r.info.status in statuses and r.info.run_id not in ids]
    else:
        runs = [r for r in runs if r.info.status in statuses]
    runs = [r for r in runs if all(r.data.tags.get(k) == str(v) for k, v in where.items())]
    runs.sort(key=lambda r: r.info.start_time or 0)
    return runs


def export_runs(
    client,
    experiment: str,
    runs: list,
    out: Path,
    selection: str,
    checkpoints: bool = False,
    replace: bool = False,
    fingerprint: Callable[[dict, str | None], list[float] | None] | None = None,
) -> Exported:
    """Write ``runs`` (of ``experiment``) as a bundle in ``out``: a new or empty folder, or with
    ``replace`` an earlier bundle (a study's, written again when it ends again).

    Written beside ``out`` first and renamed into place: an export that fails or is stopped
    leaves no half-written bundle. ``fingerprint(tags, config)``: the update's fingerprint of a
    run (:mod:`walkers.analysis.fingerprint`), kept with it where the run has none yet; where it
    cannot be had (today's code did not train the run) the earlier bundle's is kept."""
    out = Path(out)
    earlier_bundle = (out / RUNS_FILE).is_file()
    recorded: dict[str, dict] = {}
    if replace and earlier_bundle:  # swapped below, once the new one is whole
        recorded = _recorded_fingerprints(out)
    elif earlier_bundle:
        raise ConfigError(
            f"out={str(out)!r} holds a bundle already: pass replace=true to write it anew, or "
            "export into a new folder"
        )
    elif out.exists() and any(out.iterdir()):
        raise ConfigError(f"out={str(out)!r} is not empty: export into a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    with (
        no_progress_bars(),
        tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as tmp,
    ):
        staging = Path(tmp) / "bundle"
        staging.mkdir()
        records = [_run_record(client, run, staging, checkpoints, fingerprint) for run in runs]
        origins = {run.info.run_id: origin_of(run) for run in runs}
        for record in records:  # a copy's parent is named as its origin, as the run is
            parent = record["tags"].get("mlflow.parentRunId")
            if parent in origins:
                record["tags"]["mlflow.parentRunId"] = origins[parent]
        for record in records:
            if not record["fingerprint"]:
                record["fingerprint"] = _same_training(record, recorded.get(record["origin"]))
        document = {
            "format": FORMAT,
            "version": VERSION,
            "created": int(time.time()),
            "source": {"experiment": experiment, "selection": selection, "runs": len(records)},
            "runs": records,
        }
        with gzip.open(staging / RUNS_FILE, "wt", encoding="utf-8", compresslevel=9) as f:
            json.dump(document, f, separators=(",", ":"))
        if out.exists():
            out.rename(Path(tmp) / "earlier")  # removed with the staging folder
        staging.rename(out)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return Exported(out, len(records), size)


def _run_record(client, run, staging: Path, checkpoints: bool, fingerprint) -> dict:
    info, data = run.info, run.data
    config = _text_artifact(client, info.run_id, CONFIG_ARTIFACT)
    record = {
        "origin": origin_of(run),
        "run_name": info.run_name,
        "status": info.status,
        "start_time": info.start_time,
        "end_time": info.end_time,
        "params": dict(data.params),
        "tags": dict(data.tags),
        "metrics": histories.encode(
            {key: client.get_metric_history(info.run_id, key) for key in data.metrics}
        ),
        "config": config,
        "fingerprint": fingerprint and fingerprint(data.tags, config),
        "artifacts": [],
    }
    if checkpoints:
        record["artifacts"] = _copy_checkpoints(client, info.run_id, staging, record["origin"])
    return record


def _recorded_fingerprints(out: Path) -> dict[str, dict]:
    """The earlier bundle's runs that carry a fingerprint, by origin (an unreadable earlier
    bundle gives none: it is replaced whole)."""
    try:
        runs = read_bundle(out)["runs"]
    except ConfigError:
        return {}
    return {record["origin"]: record for record in runs if record.get("fingerprint")}


def _same_training(record: dict, earlier: dict | None) -> list[float] | None:
    """The earlier record's fingerprint, recorded by the code that trained the run, if the run
    has not been trained since (the same end, status and steps logged): an export by later code
    must not lose it, and a run trained on (by other code, maybe) must not keep it."""
    if earlier is None:
        return None
    logged = LOGGED_THROUGH_TAG
    untouched = (
        record["end_time"] == earlier.get("end_time")
        and record["status"] == earlier.get("status")
        and record["tags"].get(logged) == earlier["tags"].get(logged)
    )
    return earlier["fingerprint"] if untouched else None


def _text_artifact(client, run_id: str, name: str) -> str | None:
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = client.download_artifacts(run_id, name, tmp)
        except MlflowException:  # a run that never logged it (killed while opening); a store
            return None  # that fails otherwise fails the export, not a bundle without configs
        return Path(path).read_text()


def _copy_checkpoints(client, run_id: str, staging: Path, origin: str) -> list[dict]:
    names = [f.path for f in client.list_artifacts(run_id, CHECKPOINTS) if not f.is_dir]
    if not names:
        return []
    listed = []
    for name in names:
        local = staging / ARTIFACTS_DIR / origin / name
        local.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as tmp:
            shutil.move(client.download_artifacts(run_id, name, tmp), local)
        listed.append(
            {"path": name, "bytes": local.stat().st_size, "sha256": sha256_of(local)},
        )
    return listed
