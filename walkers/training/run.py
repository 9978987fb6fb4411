"""A training run from opening to its final status: its MLflow run and its local folder.

:class:`TrainingRun` is the one object the training command, the loops' book and resume talk to
about a run; what a training run says to MLflow goes through it (the session only connects the
client; ``make lint`` keeps the book and the loops from importing :mod:`walkers.tracking`). It
opens the run (new, or the resumed one reopened), logs and uploads, and :func:`ending` gives it
its final status on every way out; which run continues, and from which checkpoint, is
:mod:`walkers.training.resume`'s. :class:`RunFolder` is the one place the local layout is spelled::

    <work_dir>/runs/<run id>/
        config.yaml                  the resolved config (secrets redacted), also logged
        checkpoints/best.pt, last.pt uploaded to MLflow after each write
        resume/last.pt               last.pt with the replay buffer: an exact resume here
        videos/step_<step>.gif       the training gifs, uploaded
        download/                    checkpoints fetched from MLflow (resume elsewhere, evaluate)
        unlogged_metrics.jsonl       metrics MLflow never took (the store down at the end)
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from walkers import tracking
from walkers.training import checkpoints
from walkers.training.provenance import (
    WORKER_TAG,
    dataset_params,
    new_run_tags,
    resumed_code_tags,
    run_name,
    shareable,
    trial_tags,
    worker_name,
)

log = logging.getLogger("walkers")


def _resumed_tags(client, cfg: DictConfig) -> dict[str, str]:
    """What a resumed run's tags must now say: the budget it goes on to where that is not the
    one it started with (its param cannot change), and its code digests where other update code
    trained it before (said in one line: it can no longer stand as a reference arm)."""
    run = client.get_run(cfg.resume)
    budget = str(cfg.total_steps)
    tags = {}
    if tracking.total_steps_of(run) != budget:
        tags[tracking.BUDGET_TAG] = budget
    code = resumed_code_tags(run.data.tags)
    for digests in code.values():
        log.warning(
            "run %s continues under other update code than trained it so far (walkers.agents "
            "or walkers.data changed: code digests %s): its results stand, but it cannot serve "
            "as a reference arm (no update fingerprint)",
            cfg.resume,
            digests.replace("+", " then "),
        )
    return tags | code


@dataclass(frozen=True)
class Axis:
    """What the ``step`` of a run's metrics counts, its throughput metric and progress unit."""

    name: str
    rate_metric: str
    unit: str


#: online runs count env steps; offline runs gradient steps
ENV_STEP_AXIS = Axis(tracking.ENV_STEPS, "perf/sps", "step")
GRADIENT_STEP_AXIS = Axis(tracking.GRADIENT_STEPS, "perf/gradient_steps_per_s", "grad step")


@dataclass(frozen=True)
class RunFolder:
    """A run's local folder (see the module docstring for what lives where)."""

    root: Path

    @classmethod
    def of(cls, work_dir, run_id: str) -> RunFolder:
        return cls(Path(work_dir) / "runs" / run_id)

    @property
    def config_yaml(self) -> Path:
        return self.root / "config.yaml"

    def checkpoint(self, name: str) -> Path:
        """``checkpoints/<name>``: the copy uploaded to MLflow (no replay buffer by default)."""
        return self.root / "checkpoints" / name

    @property
    def resume_checkpoint(self) -> Path:
        """``last.pt`` with everything a resume needs (the replay buffer included), kept here."""
        return self.root / "resume" / "last.pt"

    def video(self, step: int) -> Path:
        return self.root / "videos" / f"step_{step:08d}.gif"

    @property
    def download(self) -> Path:
        return self.root / "download"


class TrainingRun:
    """One training run: its MLflow run (a :class:`~walkers.tracking.Tracker`) and its folder."""

    def __init__(self, tracker: tracking.Tracker, folder: RunFolder):
        self.tracker, self.folder = tracker, folder
        tracker.spool_dir = folder.root  # what MLflow never takes is kept with the run

    # --- opening ------------------------------------------------------------------------------
    @classmethod
    def open(
        cls, client, cfg: DictConfig, axis: Axis, data=None, extra_tags: dict | None = None
    ) -> TrainingRun:
        """The resumed run (``cfg.resume``) reopened, or a new one with the config as params and
        tags; either way with its ``config.yaml`` written and logged.

        ``axis``: what the run's steps count; ``data``: an offline run's dataset; ``extra_tags``
        are set either way (a population member: its place in the population). If opening
        fails, the run ends at once: a new run FAILED (KILLED if a signal stopped it); a resumed
        run KILLED, as it was stopped before it could go on, so that it can still be continued
        (a job run again after a store hiccup continues it).
        """
        tags = (extra_tags or {}) | trial_tags(cfg)
        if cfg.resume:
            tags |= {WORKER_TAG: worker_name()} | _resumed_tags(client, cfg)
            tracker = tracking.Tracker.reopen(client, cfg.resume, ".", resumed_training=True)
        else:
            tags = new_run_tags(cfg, axis.name, data) | tags
            tracker = tracking.Tracker.start(
                client, cfg.tracking.experiment, run_name(cfg), tags=tags, spool_dir="."
            )
        run = cls(tracker, RunFolder.of(cfg.work_dir, tracker.run_id))
        try:
            if cfg.resume:
                tracker.set_tags(tags)
            else:
                tracker.log_params(tracking.flatten(shareable(cfg)))
                if data is not None:
                    tracker.log_params(dataset_params(data, cfg.env))
            run._write_config(cfg)
        except BaseException as e:  # a signal here ends a new run KILLED too: its job reruns
            tracker.end(tracking.KILLED if cfg.resume else tracking.status_after(e))
            raise
        if cfg.tracking.get("system_metrics"):
            tracker.start_system_metrics(cfg.tracking.system_metrics_every)
        return run

    def _write_config(self, cfg: DictConfig) -> None:
        path = self.folder.config_yaml
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(OmegaConf.to_yaml(shareable(cfg)))
        self.tracker.log_artifact(path)

    @classmethod
    def attach(cls, client, work_dir, run_id: str) -> TrainingRun:
        """An existing run, to log more to (an evaluation's videos) or to end (an earlier
        attempt superseded), without reopening it."""
        return cls(tracking.Tracker.attach(client, run_id, "."), RunFolder.of(work_dir, run_id))

    # --- while it trains ----------------------------------------------------------------------
    @property
    def run_id(self) -> str:
        return self.tracker.run_id

    @property
    def logged_through(self) -> int | None:
        """The last step an earlier attempt of this run logged (a resumed run logs after it)."""
        return self.tracker.logged_through

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        self.tracker.log_metrics(metrics, step)

    def flush(self) -> bool:
        return self.tracker.flush()

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.tracker.set_tags(tags)

    def mark_pruned(self, step: int) -> None:
        self.tracker.set_tags({tracking.PRUNED_TAG: step})

    def save_checkpoint(self, name: str, state: dict, resume_state: dict | None = None) -> Path:
        """Write ``checkpoints/<name>`` and upload it; ``resume_state`` (``last.pt`` whole) is
        kept as the local resume copy."""
        if resume_state is not None:
            checkpoints.save(resume_state, self.folder.resume_checkpoint)
        path = checkpoints.save(state, self.folder.checkpoint(name))
        self.tracker.log_artifact(path, "checkpoints")
        return path

    def upload(self, path: Path, artifact_path: str) -> None:
        """Upload ``path`` into the run's ``artifact_path`` (kept locally if the store is down)."""
        self.tracker.log_artifact(path, artifact_path)

    # --- the end ------------------------------------------------------------------------------
    @property
    def status(self) -> str | None:
        return self.tracker.status

    def end(self, status: str) -> None:
        self.tracker.end(status)

    @property
    def url(self) -> str:
        return self.tracker.url


#: In a job's key, what each of its runs replaces by its own seed (a study's population job:
#: each member run is keyed as the single job of its seed would be).
SEED_IN_KEY = "{seed}"


def job_key_of_seed(job_key: str | None, seed: int) -> str | None:
    """The key of the job's run of ``seed``: ``job_key`` with :data:`SEED_IN_KEY` filled in."""
    return job_key.replace(SEED_IN_KEY, str(seed)) if job_key else job_key


def run_job_keys(cfg: DictConfig) -> list[str]:
    """The job key of each run the job makes: one for a single run, one per member of a
    population (the same key for all, unless it holds :data:`SEED_IN_KEY`)."""
    return [job_key_of_seed(cfg.job_key, cfg.seed + i) for i in range(cfg.population)]


@contextmanager
def ending(runs: list[TrainingRun], population: bool = False):
    """Every run in ``runs`` (a list that may grow inside the block) ends FINISHED, KILLED or
    FAILED on the way out (:func:`walkers.tracking.ending`); then the log says how each ended,
    where to see it, and the command that continues it (a population's always, a single run's
    if it was killed)."""
    try:
        with tracking.ending(runs):
            yield
    finally:
        for run in runs:
            log.info("MLflow run %s ended %s", run.run_id, run.status)
            log.info("open it: `make ui`, then %s", run.url)
        if population and runs:
            ids = ",".join(run.run_id for run in runs)
            log.info("continue them together: python -m walkers.train 'resume=[%s]'", ids)
        elif runs and runs[0].status == tracking.KILLED:
            log.info("continue it: python -m walkers.train resume=%s", runs[0].run_id)
