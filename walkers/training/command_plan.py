"""What one training command will do, decided once, before anything is built: its :class:`Plan`.

    plan_command(cfg, overrides) -> Plan
        nothing            the command's runs FINISHED: their result is its result
        new run(s)         one, or one per member of a population
        run(s) to continue, each from its last checkpoint, because
            resume=<id>    the user named the run (``resume=[<id>,...]``: runs together)
            a rerun        the same command ran before and its run is RUNNING, KILLED or FAILED:
                           a job's (its ``job_key``: a multirun's, a sweep's, a study's) or a
                           plain command's (its :func:`command_key`: the composed config less
                           what may change on resume)

Nothing else decides it, and the checkpoint a continued run goes on from is found here too
(:func:`last_checkpoint`: the local copy with the replay buffer, or MLflow's). The plan's record
(which runs continue, from which checkpoints) is what the session builds from. The config is
checked once (:func:`walkers.training.settings.validate`): the command's before the store is asked
anything, and where a run continues, its stored config with the overrides it takes. Each
decision the user did not ask for by name is said in one line.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import DictConfig, OmegaConf

from walkers.agents.declarations.schemas import declared_since
from walkers.errors import CheckpointError, ConfigError
from walkers.tracking.client import (
    connect,
    download_checkpoint,
    flatten,
    require_run,
    search_runs,
    tags_equal,
)
from walkers.tracking.names import FAILED, FINISHED, JOB_KEY_TAG, differing_keys
from walkers.training.bookkeeping import References, offline_references
from walkers.training.provenance import (
    COMMAND_KEY_TAG,
    DIVERGED_TAG,
    MEMBER_TAG,
    SEED_IN_KEY,
    SUPERSEDED_TAG,
    WORKER_TAG,
    code_digest,
    code_digests,
    dataset_params,
    job_key_of_seed,
    other_data,
)
from walkers.training.run import Checkpoint, RunFolder, TrainingRun, in_training_here
from walkers.training.settings import check_command, check_dataset_env, validate

if TYPE_CHECKING:  # Minari is imported only when a dataset is used
    from walkers.data.datasets import OfflineData

log = logging.getLogger("walkers")

#: Keys a continued run takes from the new command line; everything else comes from its
#: checkpoint's config.
RESUME_OVERRIDABLE = (
    "total_steps",
    "device",
    "torch_threads",
    "vector_env",
    "progress",
    "checkpoint_every",
    "log_every",
    "save_buffer",
    "work_dir",
    "video_every",
)

#: What is not part of a plain command's identity (:func:`command_key`) beside
#: :data:`RESUME_OVERRIDABLE`: the run to resume, a job's key, a sweep's trial and study (their
#: storage's password included), where the run is logged (the store and experiment it is looked
#: for in); a run's name is part of it.
NOT_THE_COMMAND = ("resume", "job_key", "algo.total_steps", "trial.", "optuna.", "tracking.")


@dataclass(frozen=True)
class Plan:
    """One command's work: ``cfg``, the session's config (validated); per run it trains (one, or
    one per member of a population) its config (``members``), the run it continues
    (``continues``: an MLflow run id, None for a new run) and the checkpoint it goes on from
    (``starts``); ``data``, an offline run's data; ``finished``, the runs that already did what
    the command asks (then nothing is built); ``new_run_tags``, what a new run is tagged with."""

    cfg: DictConfig
    client: object  # an MlflowClient of cfg.tracking.uri
    members: list[DictConfig]
    continues: list[str | None]
    starts: list[Checkpoint | None]
    data: RunDataset | None
    new_run_tags: dict[str, str]
    finished: list | None = None

    @property
    def resumed(self) -> bool:
        return any(run_id is not None for run_id in self.continues)

    def finished_value(self) -> float:
        """The optimized metric of the runs that finished (their mean, for a population)."""
        values = [r.data.metrics.get(self.cfg.optimized_metric, math.nan) for r in self.finished]
        return float(np.mean(values))


@dataclass(frozen=True)
class RunDataset:
    """The dataset an offline run learns from: the data, the references its normalized scores are
    measured between, and its statistics as the params that say which data a run learned from
    (:func:`walkers.training.provenance.dataset_params`)."""

    dataset: OfflineData
    references: References

    @classmethod
    def load(cls, cfg: DictConfig) -> RunDataset:
        """``cfg.dataset``, checked against ``cfg.env``."""
        from walkers.data import datasets

        data = datasets.load_local(cfg.dataset)
        check_dataset_env(cfg, data)
        return cls(data, offline_references(cfg.env, data))

    @functools.cached_property
    def params(self) -> dict[str, str]:
        return dataset_params(self.dataset, self.references)


def plan_command(cfg: DictConfig, overrides=()) -> Plan:
    """What ``cfg`` (a composed config; ``overrides``: its command-line overrides) will do."""
    check_command(cfg)  # before anything is read or created
    if not cfg.resume:
        validate(cfg)  # before the store is asked anything
    resumed = f"resume={cfg.resume!r}" if isinstance(cfg.resume, str) else f"resume={cfg.resume}"
    client = connect(cfg.tracking.uri, looking_for=resumed if cfg.resume else None)
    run_dataset = _dataset_loader()
    if cfg.population == 1:  # the key and name of the one run: its seed's, as a member's
        cfg.job_key = job_key_of_seed(cfg.job_key, cfg.seed)
        cfg.tracking.run_name = job_key_of_seed(cfg.tracking.run_name, cfg.seed)
    key = command_key(cfg)
    new_run_tags = {COMMAND_KEY_TAG: key}
    if cfg.resume:
        run_ids = _named_runs(cfg.resume)
    else:
        earlier = _earlier_runs(client, cfg, key)
        if finished := _finished_runs(cfg, key, earlier):
            return Plan(cfg, client, [], [], [], None, new_run_tags, finished=finished)
        run_ids = _runs_to_continue(client, cfg, earlier, run_dataset)
    if run_ids:  # each run's stored config, with the overrides it takes
        cfg, members, starts = _continued(client, cfg, overrides, run_ids)
        validate(cfg)
    else:
        members = (
            [cfg] if cfg.population == 1 else [member_config(cfg, i) for i in range(cfg.population)]
        )
        run_ids, starts = [None] * len(members), [None] * len(members)
    data = run_dataset(cfg) if cfg.get("dataset") else None  # validated: iff offline
    if data is not None and cfg.resume:  # an offline run goes on learning from its own data
        _check_same_data(client, cfg, data)
    return Plan(cfg, client, members, run_ids, starts, data, new_run_tags)


def _dataset_loader() -> Callable[[DictConfig], RunDataset]:
    """:meth:`RunDataset.load`, once per dataset and env in a plan (it may ask for the data to
    compare an earlier run's with, then to learn from)."""
    loaded: dict[tuple[str, str], RunDataset] = {}

    def load(cfg: DictConfig) -> RunDataset:
        key = (cfg.dataset, cfg.env.id)
        if key not in loaded:
            loaded[key] = RunDataset.load(cfg)
        return loaded[key]

    return load


# --- the command's identity -------------------------------------------------------------------
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


def _identity(cfg: DictConfig, key: str) -> tuple[str, list[str]]:
    """The tag that tells this command's runs, and its value for each run it makes: a job's key
    (one per member of a population, the same for all unless it holds ``{seed}``), or for a
    plain command its :func:`command_key`, the same for every member."""
    if cfg.job_key:
        return JOB_KEY_TAG, [
            job_key_of_seed(cfg.job_key, cfg.seed + i) for i in range(cfg.population)
        ]
    return COMMAND_KEY_TAG, [key] * cfg.population


# --- the same command run again ---------------------------------------------------------------
def _earlier_runs(client, cfg: DictConfig, key: str) -> list:
    """The runs earlier attempts of this command left, any status."""
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        return []
    tag, keys = _identity(cfg, key)
    runs = []
    for value in dict.fromkeys(keys):
        runs += search_runs(client, experiment.experiment_id, tags_equal({tag: value}))
    return runs


def _finished_runs(cfg: DictConfig, key: str, earlier: list) -> list | None:
    """The FINISHED run of each of this command's runs (one, or one per member of a population),
    if earlier attempts finished them all; else None. A member's run is the single run of its
    seed, so a population whose seeds all finished alone has nothing left to train either.
    Said in one line, with what to do instead."""
    tag, keys = _identity(cfg, key)
    finished = [r for r in earlier if r.info.status == FINISHED]
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
    ids = ", ".join(run.info.run_id for run in done)
    if cfg.job_key:
        log.info("job %s already FINISHED as run(s) %s: nothing to train", cfg.job_key, ids)
        return done
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
    return done


def _runs_to_continue(
    client, cfg: DictConfig, earlier: list, run_dataset: Callable[[DictConfig], RunDataset]
) -> list[str]:
    """The runs of an earlier attempt that the same command run again continues (one per
    member), instead of starting more; none: new runs.

    A plain command run again after a Ctrl-C, a SIGTERM, a ``kill -9`` or a reboot; a multirun
    job Ray runs again when its worker died (kill -9, ``ray stop`` on the node); a trial a study
    runs again when its sweeper died (``optuna.max_retry``). The earlier attempt's run, left
    RUNNING (or KILLED), is found by its key and resumed from its last checkpoint, fetched from
    MLflow on whatever worker this is; a population's K member runs are resumed together. A run
    that ended FAILED (an error, not a divergence) is continued the same way, as a rerun of an
    A/B study asks. Without checkpoints to continue from (none yet, or a population's members
    cut at different steps) the earlier runs are marked FAILED (tagged superseded) and new ones
    start. A run a process of this machine trains now is refused.
    """
    earlier = [
        r
        for r in earlier
        if r.info.status in ("RUNNING", "KILLED")
        or (r.info.status == "FAILED" and not _gave_up_on(r))
    ]
    if not earlier:
        return []
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
    ids = [r.info.run_id for r in earlier]
    if problem:
        log.warning(
            "%s ran before as run(s) %s, %s: marked FAILED; starting anew",
            what,
            ", ".join(ids),
            problem,
        )
        supersede(client, cfg.work_dir, ids, f"{problem}: the job ran again as new run(s)")
        return []
    log.info(  # routine: a killed run's command, run again
        "%s ran before as run(s) %s (%s): continuing it from its last checkpoint",
        what,
        ", ".join(ids),
        earlier[0].info.status,
    )
    return [r.info.run_id for r in runs]


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


# --- a run continued: its stored config and last checkpoint -----------------------------------
def _named_runs(resume) -> list[str]:
    """The runs ``resume=`` names: one id, or a list of two or more to continue together."""
    if not OmegaConf.is_list(resume):
        return [str(resume)]
    run_ids = [str(run_id) for run_id in resume]
    if len(run_ids) < 2 or len(set(run_ids)) < len(run_ids):
        raise ConfigError(
            f"resume=[{','.join(run_ids)}]: a list resumes two or more different runs together "
            "as a population; pass a single run id to resume one run"
        )
    return run_ids


def _continued(
    client, cfg: DictConfig, overrides, run_ids: list[str]
) -> tuple[DictConfig, list[DictConfig], list[Checkpoint]]:
    """The session's config for continuing ``run_ids`` (one run, or several together as one
    population), and per run its stored config (with the overrides it takes) and last
    checkpoint. Runs continued together must be of one configuration, seeds aside, and at one
    step and update."""
    loaded = [_stored(client, cfg, overrides, run_id) for run_id in run_ids]
    members, starts = [c for c, _ in loaded], [s for _, s in loaded]
    if len(run_ids) == 1:
        return members[0], members, starts
    listed = f"resume=[{','.join(run_ids)}]"

    def shared_settings(member_cfg: DictConfig) -> dict:
        settings = flatten(OmegaConf.to_container(member_cfg, resolve=True))
        return {k: v for k, v in settings.items() if k not in ("seed", "resume", "job_key")}

    first = shared_settings(members[0])
    for run_id, member, start in zip(run_ids[1:], members[1:], starts[1:], strict=True):
        other = shared_settings(member)
        if differing := differing_keys([first, other]):
            key = differing[0]
            raise ConfigError(
                f"{listed}: runs {run_ids[0]} and {run_id} differ in {key} "
                f"({first.get(key)!r} vs {other.get(key)!r}); only runs of one configuration "
                "(seeds aside) continue together: resume the others alone"
            )
        for counter in ("step", "num_updates"):
            here, there = getattr(starts[0], counter), getattr(start, counter)
            if there != here:
                raise ConfigError(
                    f"{listed}: run {run_ids[0]} is at {counter} {here} and run {run_id} at "
                    f"{counter} {there}; only runs at the same step and update continue "
                    "together: resume them one by one"
                )
    population = members[0].copy()
    population.population = len(members)
    population.resume, population.job_key = run_ids, cfg.get("job_key")
    return population, members, starts


def _stored(client, cfg: DictConfig, overrides, run_id: str) -> tuple[DictConfig, Checkpoint]:
    """Run ``run_id``'s stored config (with the allowed new overrides) and its last checkpoint."""
    if in_training_here(cfg.work_dir, run_id):
        raise ConfigError(
            f"resume={run_id} is not allowed now: a process of this machine is training the run; "
            "wait for it to end, or stop it there"
        )
    require_run(client, run_id, cfg.tracking.uri, key="resume")  # a clear error if not there
    start = last_checkpoint(client, cfg.work_dir, run_id)
    stored = start.run_config()
    given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    for key in RESUME_OVERRIDABLE:
        if key in given:
            stored[key] = cfg[key]
    if "total_steps" in stored.get("algo", {}):  # a schedule over the budget (ppo's annealing)
        stored.algo.total_steps = stored.total_steps  # follows a new one
    for key in cfg:  # settings added since the run was made (e.g. seeds_per_trial): today's
        if key not in stored:
            stored[key] = cfg[key]
    # a hyperparameter declared since (PPO's num_envs, say) takes its declared default, the
    # behaviour the run had before it existed; said, as the run was not told
    added = declared_since(stored.algo)
    for name, value in added.items():
        stored.algo[name] = value
    if added:
        listed = ", ".join(f"algo.{k}={v!r}" for k, v in added.items())
        log.info("run %s predates %s: resumed with the declared default", run_id, listed)
    stored.tracking = cfg.tracking
    # a sweep job's trial and key are the current attempt's (a retried trial has a new number)
    # (a study's population job: each member keyed by its own seed)
    stored.trial, stored.job_key = cfg.trial, job_key_of_seed(cfg.get("job_key"), stored.seed)
    stored.resume = run_id
    return stored, start


def _check_same_data(client, cfg: DictConfig, data: RunDataset) -> None:
    """A continued offline run reloads its dataset by name; refuse, in one line, a dataset
    rebuilt under that name since the run started (other episodes, or another CPU's rounding):
    the run would go on learning from other data. (A rerun of its command does not get here: its
    earlier run is superseded instead, :func:`_why_not_continued`.)"""
    recorded = client.get_run(str(cfg.resume)).data.params
    difference = other_data(recorded, data.params)
    if difference:
        raise ConfigError(
            f"resume={cfg.resume} is not allowed: dataset={data.dataset.id!r} is not the data "
            f"the run learned from ({difference}): a rebuild under its name; restore that "
            "build, or train a new run"
        )


# --- a run's checkpoints, as a continued run finds them ---------------------------------------
def last_checkpoint(client, work_dir, run_id: str) -> Checkpoint:
    """Run ``run_id``'s ``last.pt``: the local resume copy (replay buffer included) where this
    machine trained the run and MLflow's is not newer, else the one uploaded to MLflow."""
    folder = RunFolder.of(work_dir, run_id)
    local = folder.resume_checkpoint
    try:
        uploaded = download_checkpoint(client, run_id, "last.pt", folder.download)
    except CheckpointError:  # never uploaded (e.g. the store was down): the local copy will do
        if not local.is_file():
            raise
        uploaded = None
    uploaded = Checkpoint.read(uploaded) if uploaded is not None else None  # damaged: an error
    if local.is_file():
        whole = Checkpoint.read(local)
        if uploaded is None or whole.step >= uploaded.step:
            log.info("resuming from %s (with its replay buffer, if the agent has one)", local)
            return whole
        log.warning(
            "%s is at step %d, MLflow's last.pt at step %d: resuming from MLflow's",
            local,
            whole.step,
            uploaded.step,
        )
    return uploaded


def has_checkpoint(client, work_dir, run_id: str) -> bool:
    """Whether run ``run_id`` left a ``last.pt`` to continue from (uploaded, or kept here)."""
    uploaded = [a.path for a in client.list_artifacts(run_id, "checkpoints")]
    return (
        "checkpoints/last.pt" in uploaded
        or RunFolder.of(work_dir, run_id).resume_checkpoint.is_file()
    )


def supersede(client, work_dir, run_ids: list[str], why: str) -> None:
    """End earlier runs a new attempt replaces: FAILED, tagged with ``why``."""
    for run_id in run_ids:
        run = TrainingRun.attach(client, work_dir, run_id)
        run.set_tags({SUPERSEDED_TAG: why})
        run.end(FAILED)
