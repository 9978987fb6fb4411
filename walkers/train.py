"""``python -m walkers.train``: train one agent on one environment, logged to MLflow.

    python -m walkers.train algo=td3 env=walker2d seed=3 total_steps=300000
    python -m walkers.train resume=<mlflow run id>
    python -m walkers.train 'resume=[<id>,<id>]'      # a population's members, together again
    python -m walkers.train --help | --cfg job

The session itself is :func:`walkers.training.session.run_training`; this returns the value of
``optimized_metric`` (what an Optuna sweep optimizes).
"""

from __future__ import annotations

import math
import os
import shutil
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.cli import exit_on_bad_overrides, jobs_at_once, renamed_overrides
from walkers.errors import CheckpointError, ConfigError
from walkers.interrupts import RunsStopped, stop_cleanly_on_signals
from walkers.tracking.names import MULTIRUN_JOB_TAG

__all__ = ["main", "train"]


def train(cfg: DictConfig, overrides: list[str] | tuple = (), tags: dict | None = None) -> float:
    """The training session (:func:`walkers.training.session.run_training`), a sweep's trial
    reporting each evaluation to its Optuna study (pruning included). Imported on first use:
    torch and MLflow take seconds to import, and a typo on the command line is refused before
    either is needed."""
    from walkers.training.session import run_training

    return run_training(cfg, overrides, tags, reporter=trial_reporter)


def trial_reporter(cfg: DictConfig):
    """What a run's evaluations report to: its Optuna trial's reporter, or None outside a
    sweep."""
    if cfg.trial.id is None:
        return None
    from walkers.tuning.trial import TrialReporter

    return TrialReporter(cfg.trial, cfg.get("pruner"), cfg.seed, cfg.seeds_per_trial)


def settings_checked(cfg: DictConfig) -> None:
    """A command's values checked before Hydra writes its output folder: a refused value
    creates nothing (what needs the store, a run to continue say, is checked in the job)."""
    from walkers.training.settings import validate

    if not cfg.resume:  # a resumed run's values are its stored config's, read from the store
        validate(cfg, warn=False)


def forget_output_dir() -> None:
    """A refused run leaves nothing: the output folder Hydra made for it (its ``.hydra/`` and
    the job's log, whose lines went to the console too) goes, and the folders above it that are
    left empty, up to the working directory."""
    hydra_cfg = HydraConfig.get()
    if hydra_cfg.mode != RunMode.RUN or not hydra_cfg.output_subdir:
        return
    out, cwd = Path(hydra_cfg.runtime.output_dir).resolve(), Path.cwd().resolve()
    hydra_files = {hydra_cfg.output_subdir, f"{hydra_cfg.job.name}.log"}
    if out == cwd or cwd not in out.parents or not out.is_dir():
        return
    if {p.name for p in out.iterdir()} - hydra_files:
        return  # something of the run's own: keep it
    shutil.rmtree(out)
    for folder in out.parents:
        if folder == cwd or any(folder.iterdir()):
            break
        folder.rmdir()


def parallel_jobs() -> int:
    """How many jobs Hydra's launcher runs at once on this machine (a cluster's: one here)."""
    return jobs_at_once(HydraConfig.get().launcher) or 1


class JobFailed(RuntimeError):
    """A job on a cluster worker failed for a reason a retry cannot fix (bad input)."""


def fail(message: str, exit_code: int):
    """End the job: one line and an exit code, or, in a job a cluster worker runs (Ray,
    submitit), an exception that Hydra hands back to the launcher as the job's failure: an exit
    there looks like a dead worker, and the cluster would run the job again."""
    launcher = HydraConfig.get().launcher.get("_target_", "")
    if any(remote in launcher for remote in ("hydra_ray_launcher", "hydra_submitit_launcher")):
        raise JobFailed(message)
    if exit_code == 2:  # refused: bad input creates nothing
        forget_output_dir()
    print(message, file=sys.stderr)
    sys.exit(exit_code)


@hydra.main(config_path=str(CONF_DIR), config_name="train", execution_whitelist=["walkers.*"])
def main(cfg: DictConfig) -> float:
    from walkers.training.bookkeeping import TrainingDiverged

    stop_cleanly_on_signals()  # in a worker process too: SIGTERM ends the run like Ctrl-C
    hydra_cfg = HydraConfig.get()
    study = hydra_cfg.runtime.choices.get("ab")
    if hydra_cfg.mode == RunMode.RUN and study not in (None, "null"):
        fail(
            f"error: ab={study} is an A/B study: run it with -m (python -m walkers.train -m "
            f"ab={study})",
            2,
        )
    tags = {}
    if hydra_cfg.mode == RunMode.MULTIRUN:
        job = f"{hydra_cfg.sweep.dir}#{hydra_cfg.job.num}"
        # how this multirun's driver finds the job's run if it stops first (any job_key)
        tags[MULTIRUN_JOB_TAG] = job
        # the same for every attempt of this job (a cluster runs a job again if its worker dies)
        cfg.job_key = cfg.job_key or job
    jobs = parallel_jobs()
    if cfg.torch_threads is None and jobs > 1:  # parallel jobs share the cores
        cfg.torch_threads = max(1, (os.cpu_count() or 1) // jobs)
    try:
        return train(cfg, HydraConfig.get().overrides.task, tags)
    except (ConfigError, CheckpointError) as e:
        fail(f"error: {e}", 2)
    except TrainingDiverged as e:
        if cfg.trial.id is not None:
            print(f"error: {e}; MLflow run marked FAILED", file=sys.stderr)
            return math.nan  # the sweeper scores a diverged trial as the worst one so far
        fail(f"error: {e}; MLflow run marked FAILED", 3)
    except RunsStopped as e:  # it says which runs it ended, and how they continue
        print(f"interrupted: {e}", file=sys.stderr)
        sys.exit(130)
    except KeyboardInterrupt:
        print("interrupted: before a run started: nothing to continue", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    # SIGTERM ends a multirun's driver like Ctrl-C: its sweeper and Hydra callbacks end what it
    # started (its trials, its jobs' runs) instead of dying in place, and a second signal waits
    stop_cleanly_on_signals()
    sys.argv[1:] = renamed_overrides(sys.argv[1:])
    # a sweep's and a study's sweepers check their jobs' values themselves, in their own words
    swept = any(o.split("=", 1)[0].lstrip("+") in ("sweeps", "ab") for o in sys.argv[1:])
    exit_on_bad_overrides("train", check=None if swept else settings_checked)
    try:
        main()
    except KeyboardInterrupt:  # a plain multirun's driver (a run and a study say it themselves)
        multirun = any(a in ("-m", "--multirun") for a in sys.argv[1:])
        print(
            "interrupted: multirun stopped, its jobs' unfinished runs marked KILLED; "
            "the same command continues them"
            if multirun
            else "interrupted before the run started",  # e.g. Ctrl-C while Hydra composes
            file=sys.stderr,
        )
        sys.exit(130)
