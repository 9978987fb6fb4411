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

import contextlib
import gzip
import hashlib
import json
import logging
import shutil
import tempfile
import time
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from mlflow.entities import Metric, Param, Run, RunData, RunInfo, RunTag
from mlflow.exceptions import MlflowException

from walkers.errors import ConfigError
from walkers.tracking import histories
from walkers.tracking.client import (
    get_or_create_experiment,
    no_progress_bars,
    search_runs,
    tags_equal,
)
from walkers.tracking.names import (
    FINISHED,
    JOB_KEY_TAG,
    KILLED,
    KIND_TAG,
    LOGGED_THROUGH_TAG,
    ORIGIN_TAG,
    STUDY_KIND,
    STUDY_TAG,
    study_jobs_prefix,
    study_of_job_key,
)

log = logging.getLogger("walkers")

FORMAT = "walkers-bundle"
VERSION = 1
RUNS_FILE = "runs.json.gz"
ARTIFACTS_DIR = "artifacts"
#: Tag: the bundle an imported run came from.
IMPORTED_FROM_TAG = "walkers.imported_from"
#: Tag of a run whose import is under way (removed when it completes; an import interrupted by
#: kill -9 leaves it, and the next import deletes that run and imports it again).
IMPORTING_TAG = "walkers.importing"
#: Tag: the update's fingerprint a bundle carried for a run (kept when it travels on).
FINGERPRINT_TAG = "walkers.update_fingerprint"
#: Tag: the logged-through mark an imported run arrived with: where it still equals the run's
#: own, nobody trained it on here, and a later bundle's version of it may replace it.
IMPORTED_THROUGH_TAG = "walkers.imported_through"
#: The artifacts every run carries in its bundle (small, text); checkpoints only on request.
CONFIG_ARTIFACT = "config.yaml"
CHECKPOINTS = "checkpoints"
#: MLflow's per-call limits of log_batch.
_BATCH = {"metrics": 1000, "params": 100, "tags": 100}


@dataclass
class Exported:
    path: Path
    runs: int
    bytes: int


@dataclass
class Imported:
    experiment_id: str
    added: list[str]  # run ids created in the target store (those that replaced copies too)
    present: int  # runs of the bundle already there
    updated: int = 0  # earlier imported copies replaced by the bundle's later version


def _origin(run) -> str:
    return run.data.tags.get(ORIGIN_TAG, run.info.run_id)


# --- export -----------------------------------------------------------------------------------
def select_runs(
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
    run (:mod:`walkers.agents.fingerprint`), kept with it where the run has none yet; where it
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
        origin_of = {run.info.run_id: _origin(run) for run in runs}
        for record in records:  # a copy's parent is named as its origin, as the run is
            parent = record["tags"].get("mlflow.parentRunId")
            if parent in origin_of:
                record["tags"]["mlflow.parentRunId"] = origin_of[parent]
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
        "origin": _origin(run),
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
            {"path": name, "bytes": local.stat().st_size, "sha256": _sha256(local)},
        )
    return listed


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# --- reading ----------------------------------------------------------------------------------
def read_bundle(path: Path) -> dict:
    """The bundle's document, checked: its format, version and artifacts; a truncated or
    foreign file is refused in one line."""
    path = Path(path)
    runs_file = path / RUNS_FILE if path.is_dir() else path
    if not runs_file.is_file():
        raise ConfigError(f"bundle={str(path)!r} is not a bundle: it has no {RUNS_FILE}")
    try:
        with gzip.open(runs_file, "rt", encoding="utf-8") as f:
            document = json.load(f)
    except (EOFError, OSError, zlib.error, UnicodeDecodeError) as e:
        raise ConfigError(
            f"bundle={str(path)!r} is truncated or corrupt ({e}): nothing imported"
        ) from None
    except json.JSONDecodeError as e:
        raise ConfigError(
            f"bundle={str(path)!r} is not a walkers bundle ({e}): nothing imported"
        ) from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise ConfigError(f"bundle={str(path)!r} is not a walkers bundle (format {FORMAT!r})")
    if document.get("version") != VERSION:
        raise ConfigError(
            f"bundle={str(path)!r} is version {document.get('version')!r}: this walkers reads "
            f"version {VERSION} (export it again with this version, or update walkers)"
        )
    runs = document.get("runs")
    if not isinstance(runs, list) or len(runs) != document.get("source", {}).get("runs"):
        raise ConfigError(f"bundle={str(path)!r} is incomplete: its run count does not match")
    for record in runs:
        for artifact in record.get("artifacts", []):
            local = runs_file.parent / ARTIFACTS_DIR / record["origin"] / artifact["path"]
            if not local.is_file() or _sha256(local) != artifact["sha256"]:
                raise ConfigError(
                    f"bundle={str(path)!r}: {ARTIFACTS_DIR}/{record['origin']}/"
                    f"{artifact['path']} is missing or damaged (sha256): nothing imported"
                )
    for record in runs:
        try:
            record["history"] = histories.decode(record["metrics"])
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(
                f"bundle={str(path)!r}: run {record.get('origin')}'s metrics are damaged ({e}): "
                "nothing imported"
            ) from None
    document["root"] = str(runs_file.parent)
    return document


def _metrics(record: dict) -> Iterable[Metric]:
    for points in record["history"].values():
        yield from points


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
    by_origin = {_origin(run): run for run in existing}
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
        for chunk in _chunks(params, _BATCH["params"]):
            client.log_batch(run_id, params=chunk)
        for chunk in _chunks(list(_metrics(record)), _BATCH["metrics"]):
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
        for chunk in _chunks(tag_list, _BATCH["tags"]):
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


# --- a bundle read as a store ------------------------------------------------------------------
class BundleRuns:
    """A bundle's runs as MLflow run entities, and their metric histories, read without a
    store: what ``walkers.compare`` takes a reference arm from. Each run's id is its origin."""

    def __init__(self, path: Path, label_key: str | None = None, arm: str | None = None) -> None:
        """``label_key``: a param every run gets, valued the bundle's name (what keeps its
        runs apart from a store's runs of the same configuration); ``arm``: only the runs of
        that arm of the study that made the bundle (job keys ``ab/<study>/<arm>/...``)."""
        self.path, self.arm = Path(path), arm
        self.document = read_bundle(self.path)
        records = [r for r in self.document["runs"] if arm is None or _study_arm(r) == arm]
        if arm is not None and not records:
            raise ConfigError(f"bundle={str(path)!r} holds no run of a study arm {arm!r}")
        self.records = {record["origin"]: record for record in records}
        label = {label_key: self.name} if label_key else {}
        self.runs = [_as_run(record, label) for record in records]

    @property
    def name(self) -> str:
        folder = self.path.name if self.path.is_dir() else self.path.parent.name
        return folder + (f"#{self.arm}" if self.arm else "")

    def get_metric_history(self, run_id: str, key: str) -> list[Metric]:
        return list(self.records[run_id]["history"].get(key, []))


def _study_arm(record: dict) -> str | None:
    """The arm of the study that made a run (its job key ``ab/<study>/<arm>/<env>/<seed>``)."""
    place = study_of_job_key(record["tags"].get(JOB_KEY_TAG, ""))
    return place[1] if place else None


def _as_run(record: dict, extra_params: dict[str, str]) -> Run:
    latest = [
        max(points, key=lambda m: (m.step, m.timestamp))
        for points in record["history"].values()
        if points
    ]
    info = RunInfo(
        run_id=record["origin"],
        experiment_id="bundle",
        user_id="",
        status=record["status"],
        start_time=record["start_time"],
        end_time=record["end_time"],
        lifecycle_stage="active",
        run_name=record["run_name"],
    )
    data = RunData(
        metrics=latest,
        params=[Param(k, v) for k, v in (record["params"] | extra_params).items()],
        tags=[RunTag(k, v) for k, v in record["tags"].items()],
    )
    return Run(info, data)
