"""The results bundle's format (:mod:`walkers.tracking.bundles` says what a bundle is): its
names, what an export and an import report, a bundle read back, and a bundle read as a store."""

from __future__ import annotations

import gzip
import hashlib
import json
import logging
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from mlflow.entities import Metric, Param, Run, RunData, RunInfo, RunTag

from walkers.errors import ConfigError
from walkers.tracking import histories
from walkers.tracking.names import (
    JOB_KEY_TAG,
    ORIGIN_TAG,
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
BATCH = {"metrics": 1000, "params": 100, "tags": 100}


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


def origin_of(run) -> str:
    return run.data.tags.get(ORIGIN_TAG, run.info.run_id)


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
            if not local.is_file() or sha256_of(local) != artifact["sha256"]:
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


def metrics_of(record: dict) -> Iterable[Metric]:
    for points in record["history"].values():
        yield from points


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


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
