"""The names walkers gives things in MLflow: run statuses, tags, the axes a run's steps count.
Plain constants: importing them imports nothing else (no MLflow)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

#: Statuses a run ends with.
FINISHED, FAILED, KILLED = "FINISHED", "FAILED", "KILLED"


def status_after(error: BaseException) -> str:
    """The status of a run that ``error`` ended: KILLED after Ctrl-C (or SIGTERM turned into
    it), wherever it landed, so that the same command continues it; FAILED after anything else."""
    return KILLED if isinstance(error, KeyboardInterrupt) else FAILED


#: Tag that marks runs which are not training runs (reports, sweep parents, datasets).
KIND_TAG = "walkers.kind"
#: Run tag naming what the step of a run's metrics counts; runs without it count env steps.
X_AXIS_TAG = "walkers.x_axis"
ENV_STEPS, GRADIENT_STEPS = "env_steps", "gradient_steps"
#: Tag of a run its pruner stopped early (a sweep trial; ``walkers.compare`` leaves it out).
PRUNED_TAG = "walkers.pruned_at_step"
#: Tag: why a run was ended by someone else than its job (its driver or sweeper, on the way out).
END_REASON_TAG = "walkers.end_reason"
#: Tag: what identifies a multirun job across attempts (``job_key``, set by walkers.train).
JOB_KEY_TAG = "walkers.job_key"
#: Tag: the multirun a job's run belongs to in this attempt (``<sweep dir>#<job number>``), set
#: whatever its ``job_key``: how the multirun's driver finds the runs its jobs left RUNNING.
MULTIRUN_JOB_TAG = "walkers.multirun_job"
#: Tag: the last step whose metrics reached MLflow (a resumed run logs only steps after it).
LOGGED_THROUGH_TAG = "walkers.logged_through"
#: Tag: the budget a run was continued to (``resume=<id> total_steps=N``) where it is not the
#: ``total_steps`` param it started with (MLflow writes a param once): what it trained for.
BUDGET_TAG = "walkers.total_steps"


def total_steps_of(run) -> str | None:
    """The budget a run trained for: its ``total_steps`` param, or the one it was continued to."""
    return run.data.tags.get(BUDGET_TAG) or run.data.params.get("total_steps")


#: Tags of an A/B study's own run: ``walkers.kind=ab`` and ``walkers.ab=<study name>``; the runs
#: it trains nest under it (``mlflow.parentRunId``), and every run it counts carries its job key
#: (:func:`study_job_key`), wherever it was trained.
STUDY_KIND, STUDY_TAG = "ab", "walkers.ab"


def study_job_key(study: str, arm: str, env: str, seed: int) -> str:
    """A study's job key, ``ab/<study>/<arm>/<env>/<seed>``: what finds a job's run again,
    whichever command (or store it was imported from) made it."""
    return f"{study_jobs_prefix(study)}{arm}/{env}/{seed}"


def study_jobs_prefix(study: str) -> str:
    """What every job key of ``study`` starts with."""
    return f"{STUDY_KIND}/{study}/"


def study_of_job_key(key: str) -> tuple[str, str, str, int] | None:
    """``(study, arm, env, seed)`` of a study's job key, else None."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != STUDY_KIND or not parts[4].isdigit():
        return None
    return parts[1], parts[2], parts[3], int(parts[4])


#: Tag: the run id in the store a run was first logged to (set on every copy a bundle imports).
ORIGIN_TAG = "walkers.origin"


#: How a key a run does not have is shown (a key added to the config after the run).
ABSENT = "(not set)"


def differing_keys(configs: Sequence[Mapping[str, str]]) -> list[str]:
    """Keys whose value is not the same in every (flattened) config, a missing key counting as
    a value, sorted."""
    keys = set().union(*configs) if configs else set()
    return sorted(k for k in keys if len({c.get(k, ABSENT) for c in configs}) > 1)
