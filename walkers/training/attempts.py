"""The same command run again: a job's (its ``job_key``: a multirun's, a sweep's, a study's) or
a plain command's (its :func:`command_key`: the composed config less what may change on resume).
Its FINISHED runs are its result, nothing is trained (:func:`finished_attempts`); a RUNNING,
KILLED or FAILED one is continued (:func:`continue_earlier_attempt`), unless a process of this
machine trains it now; each said in one line. New runs are keyed here too (:func:`member_config`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import socket
from collections.abc import Callable
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from walkers.errors import ConfigError
from walkers.tracking.client import flatten, search_runs, tags_equal
from walkers.tracking.names import FINISHED, JOB_KEY_TAG
from walkers.training.provenance import (
    COMMAND_KEY_TAG,
    DIVERGED_TAG,
    MEMBER_TAG,
    SEED_IN_KEY,
    SUPERSEDED_TAG,
    WORKER_TAG,
    code_digests,
    job_key_of_seed,
    other_data,
)
from walkers.training.resume import RESUME_OVERRIDABLE
from walkers.training.run import has_checkpoint, in_training_here, last_checkpoint, supersede
from walkers.training.run_dataset import RunDataset

log = logging.getLogger("walkers")

#: What is not part of a plain command's identity (:func:`command_key`) beside
#: :data:`RESUME_OVERRIDABLE`: the run to resume, a job's key, a sweep's trial and study (their
#: storage's password included), where the run is logged (the store and experiment it is looked
#: for in); a run's name is part of it.
NOT_THE_COMMAND = ("resume", "job_key", "algo.total_steps", "trial.", "optuna.", "tracking.")


@dataclass(frozen=True)
class Attempt:
    """What the store says of this command: ``cfg``, the command's config (``resume`` set where it
    continues an earlier attempt's run(s)); ``key``, its :func:`command_key`, for new runs' tags;
    ``finished``: the runs that already did what it asks (then nothing is trained); ``members``:
    the configs of the new runs it would start (one per member)."""

    cfg: DictConfig
    key: str
    finished: list | None = None

    @property
    def members(self) -> list[DictConfig]:
        k = self.cfg.population
        return [self.cfg] if k == 1 else [member_config(self.cfg, i) for i in range(k)]


def of_command(client, cfg: DictConfig, run_dataset: Callable[[DictConfig], RunDataset]) -> Attempt:
    """What ``cfg`` (without ``resume=``) finds of itself in the store: runs that FINISHED, a
    run to continue (``resume`` set on the config), or nothing (new runs). ``run_dataset`` loads
    an offline run's data (once a session)."""
    if cfg.population == 1:  # the key and name of the one run: its seed's, as a member's
        cfg.job_key = job_key_of_seed(cfg.job_key, cfg.seed)
        cfg.tracking.run_name = job_key_of_seed(cfg.tracking.run_name, cfg.seed)
    key = command_key(cfg)
    if cfg.resume:
        return Attempt(cfg, key)
    done = finished_attempts(client, cfg, key)
    if done:
        return Attempt(cfg, key, finished=done)
    return Attempt(continue_earlier_attempt(client, cfg, key, run_dataset), key)


def command_key(cfg: DictConfig) -> str:
    """What identifies "the same command" of a plain run: a digest of the composed config, less
    :data:`RESUME_OVERRIDABLE` and :data:`NOT_THE_COMMAND` (``tracking.run_name`` counts)."""
    settings = flatten(OmegaConf.to_container(cfg, resolve=True))
    kept = {key: value for key, value in settings.items() if _in_the_command(key)}
    text = json.dumps(kept, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _in_the_command(key: str) -> bool:
    if key == "tracking.run_name":
        return True
    excluded = any(key == p or (p.endswith(".") and key.startswith(p)) for p in NOT_THE_COMMAND)
    return key not in RESUME_OVERRIDABLE and not excluded


def member_config(cfg: DictConfig, i: int) -> DictConfig:
    """Member ``i``'s config: seed ``seed + i``, and ``population=1`` (what resuming it means);
    a job key or run name with ``{seed}`` in it gets the member's seed there (a study's jobs)."""
    member = cfg.copy()
    member.seed = cfg.seed + i
    member.population = 1
    member.job_key = job_key_of_seed(cfg.job_key, member.seed)
    if SEED_IN_KEY in (cfg.tracking.run_name or ""):
        member.tracking.run_name = job_key_of_seed(cfg.tracking.run_name, member.seed)
    elif cfg.tracking.run_name:
        member.tracking.run_name = f"{cfg.tracking.run_name}-m{i}"
    return member


def run_job_keys(cfg: DictConfig) -> list[str]:
    """The job key of each run the job makes: one for a single run, one per member of a
    population (the same key for all, unless it holds :data:`SEED_IN_KEY`)."""
    return [job_key_of_seed(cfg.job_key, cfg.seed + i) for i in range(cfg.population)]


# --- the same command run again ---------------------------------------------------------------
def _identity(cfg: DictConfig, key: str) -> tuple[str, list[str]]:
    """The tag that tells this command's runs, and its value for each run it makes: a job's key
    (one per member of a population, the same for all unless it holds ``{seed}``), or for a
    plain command its :func:`command_key`, the same for every member."""
    if cfg.job_key:
        return JOB_KEY_TAG, run_job_keys(cfg)
    return COMMAND_KEY_TAG, [key] * cfg.population


def _attempts(client, cfg: DictConfig, key: str) -> list:
    """The runs earlier attempts of this command left, any status."""
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        return []
    tag, keys = _identity(cfg, key)
    runs = []
    for value in dict.fromkeys(keys):
        query = tags_equal({tag: value})
        runs += search_runs(client, experiment.experiment_id, query)
    return runs


def finished_attempts(client, cfg: DictConfig, key: str) -> list | None:
    """The FINISHED run of each of this command's runs (one, or one per member of a population),
    if earlier attempts finished them all; else None. A member's run is the single run of its
    seed, so a population whose seeds all finished alone has nothing left to train either.
    Said in one line, with what to do instead."""
    tag, keys = _identity(cfg, key)
    finished = [r for r in _attempts(client, cfg, key) if r.info.status == FINISHED]
    shared_key = len(set(keys)) < len(keys)  # members told apart by their tag
    done = []
    for member, value in enumerate(keys):
        runs = [
            r
            for r in finished
            if r.data.tags.get(tag) == value
            and (not shared_key or r.data.tags.get(MEMBER_TAG) == str(member))
        ]
        if not runs:
            return None
        done.append(runs[0])
    _say_finished(cfg, done)
    return done


def _say_finished(cfg: DictConfig, done: list) -> None:
    ids = ", ".join(run.info.run_id for run in done)
    if cfg.job_key:
        log.info("job %s already FINISHED as run(s) %s: nothing to train", cfg.job_key, ids)
        return
    from walkers.agents.fingerprint import code_digest  # torch: only when it is said

    other_code = [r.info.run_id for r in done if code_digest() not in code_digests(r.data.tags)]
    log.info(
        "this command already FINISHED as run(s) %s%s: nothing to train (more steps: "
        "resume=%s total_steps=<more>; another sample: another seed; a new run of the same "
        "config: another tracking.run_name)",
        ids,
        f", trained by other update code than this checkout's (run(s) {', '.join(other_code)})"
        if other_code
        else "",
        done[0].info.run_id if len(done) == 1 else f"[{ids.replace(', ', ',')}]",
    )


def continue_earlier_attempt(
    client, cfg: DictConfig, key: str, run_dataset: Callable[[DictConfig], RunDataset]
) -> DictConfig:
    """The same command run again continues the run(s) of its earlier attempt instead of
    starting more.

    A plain command run again after a Ctrl-C, a SIGTERM, a ``kill -9`` or a reboot; a multirun
    job Ray runs again when its worker died (kill -9, ``ray stop`` on the node); a trial a study
    runs again when its sweeper died (``optuna.max_retry``). The earlier attempt's run, left
    RUNNING (or KILLED), is found by its key and resumed from its last checkpoint, fetched from
    MLflow on whatever worker this is; a population's K member runs are resumed together
    (``resume=[...]``). A run that ended FAILED (an error, not a divergence) is continued the
    same way, as a rerun of an A/B study asks. Without checkpoints to continue from (none yet,
    or a population's members cut at different steps) the earlier runs are marked FAILED
    (tagged superseded) and new ones start.
    """
    earlier = [
        r
        for r in _attempts(client, cfg, key)
        if r.info.status in ("RUNNING", "KILLED")
        or (r.info.status == "FAILED" and not _gave_up_on(r))
    ]
    if not earlier:
        return cfg
    what = f"job {cfg.job_key}" if cfg.job_key else "this command"
    for run in earlier:
        if busy := _training_now(cfg, run):
            raise ConfigError(f"{what} {busy}")
    if cfg.population > 1:
        by_member = {int(r.data.tags.get(MEMBER_TAG, -1)): r for r in earlier}
        runs = [by_member.get(i) for i in range(cfg.population)]
    else:
        runs = earlier[:1]
    problem = _why_not_continued(client, cfg, runs, run_dataset)
    ids = [r.info.run_id for r in earlier if r is not None]
    if problem:
        log.warning(
            "%s ran before as run(s) %s, %s: marked FAILED; starting anew",
            what,
            ", ".join(ids),
            problem,
        )
        supersede(client, cfg.work_dir, ids, f"{problem}: the job ran again as new run(s)")
        return cfg
    log.info(  # routine: a killed run's command, run again
        "%s ran before as run(s) %s (%s): continuing it from its last checkpoint",
        what,
        ", ".join(ids),
        earlier[0].info.status,
    )
    cfg = cfg.copy()
    cfg.resume = ids[0] if cfg.population == 1 else [r.info.run_id for r in runs]
    return cfg


def _training_now(cfg: DictConfig, run) -> str | None:
    """Why an earlier attempt's run is not to be continued now: a process of this machine trains
    it (it holds the run's lock), or, for a plain command, it is RUNNING on another machine,
    which only its user can say is dead."""
    run_id, worker = run.info.run_id, run.data.tags.get(WORKER_TAG, "")
    if in_training_here(cfg.work_dir, run_id):
        return (
            f"is training now as run {run_id} in another process of this machine: wait for it "
            "to end, or stop it there (another run of the same config: another tracking.run_name)"
        )
    host = worker.split("/")[0]
    if not cfg.job_key and run.info.status == "RUNNING" and host and host != socket.gethostname():
        return (
            f"has run {run_id} RUNNING on {worker}: if it died there, continue it here with "
            f"resume={run_id}; else wait for it"
        )
    return None


def _gave_up_on(run) -> bool:
    """A FAILED run not to continue: superseded by a new attempt, or ended by divergence."""
    return SUPERSEDED_TAG in run.data.tags or DIVERGED_TAG in run.data.tags


def _why_not_continued(
    client, cfg: DictConfig, runs: list, run_dataset: Callable[[DictConfig], RunDataset]
) -> str | None:
    """Why the earlier attempt's runs (one per member, None where missing) cannot go on."""
    if any(r is None for r in runs):
        return f"which are not the {cfg.population} members of a population"
    if cfg.get("dataset"):  # an offline job: its dataset may have been rebuilt since
        difference = other_data(runs[0].data.params, run_dataset(cfg).params)
        if difference:
            return f"which learned from another build of dataset={cfg.dataset} ({difference})"
    ids = [run.info.run_id for run in runs]
    if not all(has_checkpoint(client, cfg.work_dir, run_id) for run_id in ids):
        return "which ended without a checkpoint"
    steps = set()
    if len(runs) > 1:  # members continue together only from one step
        steps = {last_checkpoint(client, cfg.work_dir, run_id).step for run_id in ids}
    if len(steps) > 1:
        return f"whose members' checkpoints are at different steps {sorted(steps)}"
    return None
