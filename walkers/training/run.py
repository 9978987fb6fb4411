"""A training run from opening to its final status: its MLflow run, its local folder and its
checkpoints.

:class:`TrainingRun` is what a run is to the training command, the loops' book and the plan: its
MLflow run, its folder, its config (in one form: resolved, without secrets) and what its steps
count. What a training run says to MLflow goes through it (the session only connects the client;
``make lint`` keeps the book and the loops from importing :mod:`walkers.tracking`). It opens the
run (new, or a continued one reopened), holds its lock while it trains, logs and uploads, and
:func:`ending_and_saying_how` gives it its final status on every way out. Which run continues,
from which checkpoint, is :mod:`walkers.training.command_plan`'s. :class:`RunFolder` is the one
place the local layout is spelled::

    <work_dir>/runs/<run id>/
        config.yaml                  the resolved config (secrets redacted), also logged
        checkpoints/best.pt, last.pt uploaded to MLflow after each write
        resume/last.pt               last.pt with the replay buffer: an exact resume here
        training.lock                held while a process trains the run (none other may)
        videos/step_<step>.gif       the training gifs, uploaded
        download/                    checkpoints fetched from MLflow (resume elsewhere, evaluate)
        unlogged_metrics.jsonl       metrics MLflow never took (the store down at the end)

A checkpoint (``last.pt``, ``best.pt``) is a :class:`Checkpoint`, the one type that writes and
reads them: written atomically, verified on read (:func:`write_checkpoint`,
:func:`read_checkpoint`), and an agent restored from one (:func:`agent_from_checkpoint`).
"""

from __future__ import annotations

import dataclasses
import fcntl
import logging
import math
import os
import tempfile
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from walkers.agents.factory import build_agent
from walkers.errors import CheckpointError, ConfigError
from walkers.interrupts import RunsStopped
from walkers.tracking.client import Tracker, ending, flatten
from walkers.tracking.names import (
    BUDGET_TAG,
    ENV_STEPS,
    GRADIENT_STEPS,
    KILLED,
    PRUNED_TAG,
    status_after,
    total_steps_of,
)
from walkers.training.envs import env_spaces
from walkers.training.provenance import (
    WORKER_TAG,
    new_run_tags,
    resumed_code_tags,
    run_name,
    shareable,
    trial_tags,
    worker_name,
)

log = logging.getLogger("walkers")


def _resumed_tags(client, run_id: str, total_steps: int) -> dict[str, str]:
    """What a continued run's tags must now say: the budget it goes on to where that is not the
    one it started with (its param cannot change), and its code digests where other update code
    trained it before (said in one line: it can no longer stand as a reference arm)."""
    run = client.get_run(run_id)
    tags = {}
    if total_steps_of(run) != str(total_steps):
        tags[BUDGET_TAG] = str(total_steps)
    code = resumed_code_tags(run.data.tags)
    for digests in code.values():
        log.warning(
            "run %s continues under other update code than trained it so far (walkers.agents "
            "or walkers.data changed: code digests %s): its results stand, but it cannot serve "
            "as a reference arm (no update fingerprint)",
            run_id,
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
ENV_STEP_AXIS = Axis(ENV_STEPS, "perf/sps", "step")
GRADIENT_STEP_AXIS = Axis(GRADIENT_STEPS, "perf/gradient_steps_per_s", "grad step")


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

    @property
    def lock(self) -> Path:
        """Locked (``flock``) while a process of this machine trains the run."""
        return self.root / "training.lock"

    def video(self, step: int) -> Path:
        return self.root / "videos" / f"step_{step:08d}.gif"

    @property
    def download(self) -> Path:
        return self.root / "download"


class TrainingRun:
    """One training run: its MLflow run (a :class:`~walkers.tracking.client.Tracker`), its
    folder, and what it is: its ``config`` (resolved and shareable: no secrets; what its params,
    ``config.yaml`` and checkpoints hold) and the ``axis`` its steps count."""

    def __init__(
        self, tracker: Tracker, folder: RunFolder, config: dict | None = None, axis=None, lock=None
    ):
        self.tracker, self.folder = tracker, folder
        tracker.spool_dir = folder.root  # what MLflow never takes is kept with the run
        self.config, self.axis = config or {}, axis or ENV_STEP_AXIS
        self._lock = lock  # the run's lock file, held while this process trains it

    # --- opening ------------------------------------------------------------------------------
    @classmethod
    def open(
        cls,
        client,
        cfg: DictConfig,
        axis: Axis,
        continues: str | None = None,
        data=None,
        extra_tags: dict | None = None,
    ) -> TrainingRun:
        """Run ``continues`` reopened, or a new one with the config as params and tags; either
        way with its ``config.yaml`` written and logged.

        ``axis``: what the run's steps count; ``data``: an offline run's
        :class:`~walkers.training.command_plan.RunDataset`; ``extra_tags``
        are set either way (a population member: its place in the population). If opening
        fails, the run ends at once: a new run FAILED (KILLED if a signal stopped it); a
        continued run KILLED, as it was stopped before it could go on, so that it can still be
        continued (a job run again after a store hiccup continues it).
        """
        tags = (extra_tags or {}) | trial_tags(cfg)
        config = shareable(cfg)
        lock = None
        if continues:  # locked before it is reopened: a run another process trains is left be
            lock = hold_lock(RunFolder.of(cfg.work_dir, continues))
            try:
                tags |= {WORKER_TAG: worker_name()} | _resumed_tags(
                    client, continues, cfg.total_steps
                )
                tracker = Tracker.reopen(client, continues, ".", resumed_training=True)
            except BaseException:
                lock.close()
                raise
        else:
            tags = new_run_tags(cfg, axis.name, data) | tags
            tracker = Tracker.start(
                client, cfg.tracking.experiment, run_name(cfg), tags=tags, spool_dir="."
            )
        run = cls(tracker, RunFolder.of(cfg.work_dir, tracker.run_id), config, axis, lock)
        try:
            if lock is None:
                run._lock = hold_lock(run.folder)
            if continues:
                tracker.set_tags(tags)
            else:
                tracker.log_params(flatten(config))
                if data is not None:
                    tracker.log_params(data.params)
            run._write_config()
        except BaseException as e:  # a signal here ends a new run KILLED too: its job reruns
            run.end(KILLED if continues else status_after(e))
            raise
        if cfg.tracking.get("system_metrics"):
            tracker.start_system_metrics(cfg.tracking.system_metrics_every)
        log.info("MLflow run %s: follow it live with `make ui`, then %s", run.run_id, run.url)
        return run

    def _write_config(self) -> None:
        path = self.folder.config_yaml
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(OmegaConf.to_yaml(self.config))
        self.tracker.log_artifact(path)

    @classmethod
    def attach(cls, client, work_dir, run_id: str) -> TrainingRun:
        """An existing run, to log more to (an evaluation's videos) or to end (an earlier
        attempt superseded), without reopening it."""
        return cls(Tracker.attach(client, run_id, "."), RunFolder.of(work_dir, run_id))

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
        self.tracker.set_tags({PRUNED_TAG: step})

    def save_checkpoint(
        self, name: str, checkpoint: Checkpoint, resume_copy: Checkpoint | None = None
    ) -> Path:
        """Write ``checkpoints/<name>`` and upload it; ``resume_copy`` (``last.pt`` whole) is
        kept as the local resume copy."""
        if resume_copy is not None:
            resume_copy.write(self.folder.resume_checkpoint)
        path = checkpoint.write(self.folder.checkpoint(name))
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
        if self._lock is not None:
            self._lock.close()  # lets go of it
            self._lock = None

    @property
    def url(self) -> str:
        return self.tracker.url


def hold_lock(folder: RunFolder):
    """The run's lock, held (the open file) until the run ends or the process dies, ``kill -9``
    included: :func:`in_training_here` asks it; a run another process holds is refused."""
    folder.lock.parent.mkdir(parents=True, exist_ok=True)
    lock = open(folder.lock, "a")  # noqa: SIM115 (held until the run ends)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.close()
        raise ConfigError(
            f"run {folder.root.name} is training in another process of this machine: wait for "
            "it to end, or stop it there"
        ) from None
    return lock


def in_training_here(work_dir, run_id: str) -> bool:
    """Whether a process of this machine trains run ``run_id`` now (it holds the run's lock)."""
    path = RunFolder.of(work_dir, run_id).lock
    if not path.is_file():
        return False
    with open(path, "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(lock, fcntl.LOCK_UN)
    return False


@contextmanager
def ending_and_saying_how(runs: list[TrainingRun], population: bool = False):
    """Every run in ``runs`` (a list that may grow inside the block) ends FINISHED, KILLED or
    FAILED on the way out (:func:`walkers.tracking.client.ending`); then the log says how each
    ended, where to see it, and the command that continues it (a population's always, a single run's
    if it was killed). A Ctrl-C that ends runs says which, for the command's last line."""
    try:
        with ending(runs):
            yield
    except KeyboardInterrupt as stop:
        if runs and not isinstance(stop, RunsStopped):
            ids = ", ".join(run.run_id for run in runs)
            raise RunsStopped(
                f"MLflow run(s) {ids} marked KILLED; the same command continues from the last "
                "checkpoint"
            ) from None
        raise
    finally:
        for run in runs:
            log.info("MLflow run %s ended %s", run.run_id, run.status)
            log.info("open it: `make ui`, then %s", run.url)
        if population and runs:
            ids = ",".join(run.run_id for run in runs)
            log.info(
                "continue them together: python -m walkers.train 'resume=[%s]', or the same "
                "command",
                ids,
            )
        elif runs and runs[0].status == KILLED:
            log.info(
                "continue it: python -m walkers.train resume=%s, or the same command",
                runs[0].run_id,
            )


FORMAT_VERSION = 1


def write_checkpoint(state: dict, path: str | os.PathLike) -> Path:
    """Write ``state`` to ``path`` via a temporary file and an atomic rename.

    A crash mid-write leaves the previous checkpoint intact, never a truncated one; the temporary
    file a killed write left behind is removed by the next write of the same checkpoint.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format_version": FORMAT_VERSION, **state}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    for stale in path.parent.glob(f".{path.name}.*.tmp"):  # of a write killed mid-way (SIGKILL)
        stale.unlink(missing_ok=True)
    return path


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint written by :func:`write_checkpoint`; a damaged file raises
    :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # truncated zip, wrong file type, unpickling garbage ...
        raise CheckpointError(
            f"checkpoint {str(path)!r} is corrupted or truncated ({type(e).__name__}: {e})"
        ) from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {str(path)!r} is not a walkers checkpoint")
    return state


@dataclass(frozen=True)
class Checkpoint:
    """What a run's checkpoint holds, by name (the file holds the same names, as a dict).

    ``trainer`` is the loop's progress (:class:`walkers.training.bookkeeping.Progress` as a
    dict), ``agent`` the agent's state (with or without its replay buffer), ``config`` the
    run's composed config (shareable: no secrets), ``torch_rng`` and ``cuda_rng`` torch's
    generators (:func:`walkers.seeding.torch_rng_state`), ``env_rng`` the training env's
    generator (None for a run without one: offline).
    """

    trainer: dict
    agent: dict
    config: dict
    torch_rng: torch.Tensor
    cuda_rng: list | None = None
    env_rng: dict | None = None

    @property
    def step(self) -> int:
        """The run's step when it was written (env steps; offline: gradient steps)."""
        return self.trainer["step"]

    @property
    def num_updates(self) -> int | None:
        return self.agent.get("num_updates")

    @property
    def progress(self) -> dict:
        """The loop's progress to go on from; a checkpoint from before runs counted their CPU
        time has a total that is unknown, not 0."""
        return {"cpu_seconds": math.nan} | self.trainer

    def run_config(self) -> DictConfig:
        return OmegaConf.create(self.config)

    def with_agent(self, agent: dict) -> Checkpoint:
        """This checkpoint with another agent state (the same agent with its replay buffer)."""
        return dataclasses.replace(self, agent=agent)

    def write(self, path: str | os.PathLike) -> Path:
        """Write it to ``path`` atomically (:func:`write_checkpoint`); its tensors are written,
        not copied."""
        return write_checkpoint(
            {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}, path
        )

    @classmethod
    def read(cls, path: str | os.PathLike) -> Checkpoint:
        """The checkpoint at ``path``; a damaged or foreign file raises :class:`CheckpointError`."""
        state = read_checkpoint(path)
        required = [f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING]
        if missing := [name for name in required if name not in state]:
            raise CheckpointError(
                f"checkpoint {str(path)!r} holds no {missing[0]}: not a training run's checkpoint"
            )
        return cls.of(state)

    @classmethod
    def of(cls, state: dict) -> Checkpoint:
        """A checkpoint from the dict a file holds (:func:`read_checkpoint`)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{key: value for key, value in state.items() if key in names})


def agent_from_checkpoint(checkpoint: Checkpoint | dict, env, device: str):
    """The run config stored in a checkpoint (or the dict a file holds: :func:`read_checkpoint`)
    and its agent, restored, for acting on ``env``: ``(run config, agent)``."""
    if isinstance(checkpoint, dict):
        checkpoint = Checkpoint.of(checkpoint)
    run_cfg = checkpoint.run_config()
    run_cfg.device = device
    agent = build_agent(run_cfg, env_spaces(env))
    agent.load_state_dict(checkpoint.agent)
    return run_cfg, agent
