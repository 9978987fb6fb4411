"""How a run continues: every way training picks up where a run left off, in one module, asked
once per command by the plan (:func:`continuation`).

- ``resume=<id>`` (``resume=[<id>,...]`` for a population's runs together): the run's stored
  config with the overrides allowed on resume (:func:`load_run`, :func:`load_population`);
- the same command run again: a job's (its ``job_key``: a multirun's, a sweep's, a study's) or a
  plain command's (its :func:`command_key`: the composed config less what may change on resume).
  FINISHED runs are its result (:func:`finished_attempts`); a RUNNING, KILLED or FAILED one
  continues (:func:`continue_earlier_attempt`);
- which checkpoint: the local resume copy or MLflow's, the newer (:func:`last_checkpoint`);
- an offline run goes on learning from the data it started on (:func:`check_same_data`).

The run itself is reopened by :meth:`TrainingRun.open` (``cfg.resume`` set), and the book goes on
from the checkpoint found here (:meth:`RunBook.continue_from`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import socket
from collections.abc import Callable
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from walkers import tracking
from walkers.agents.declarations.schemas import declared_since
from walkers.errors import ConfigError
from walkers.tracking import differing_keys, flatten
from walkers.training.checkpoints import Checkpoint
from walkers.training.provenance import (
    COMMAND_KEY_TAG,
    DIVERGED_TAG,
    MEMBER_TAG,
    SUPERSEDED_TAG,
    WORKER_TAG,
    code_digests,
    other_data,
)
from walkers.training.run import has_checkpoint, in_training_here, supersede
from walkers.training.run import last_checkpoint as run_last_checkpoint
from walkers.training.run_dataset import RunDataset

log = logging.getLogger("walkers")


#: Keys a resumed run takes from the new command line; everything else comes from its checkpoint.
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
class Continuation:
    """What the store says the command does: ``cfg``, the config to train (the command's, or a
    continued run's stored one with the overrides it takes); per run, its config and the
    checkpoint it goes on from (``members``; None: a new run); ``finished``: the runs that
    already did what the command asks (nothing to train); ``command_key``: the command's
    identity, for the tags of new runs."""

    cfg: DictConfig
    command_key: str
    members: list[tuple[DictConfig, Checkpoint | None]]
    finished: list | None = None

    @property
    def continued(self) -> bool:
        return any(start is not None for _, start in self.members)


def continuation(
    client, cfg: DictConfig, overrides, run_dataset: Callable[[DictConfig], RunDataset]
) -> Continuation:
    """What ``cfg`` does: continue ``resume=``, or the run(s) the same command started before
    (found by a job's key or the :func:`command_key`); nothing, if those FINISHED; else start
    new runs, one per member. ``run_dataset`` loads an offline run's data (once a session)."""
    if cfg.population == 1:  # the key and name of the one run: its seed's, as a member's
        cfg.job_key = job_key_of_seed(cfg.job_key, cfg.seed)
        cfg.tracking.run_name = job_key_of_seed(cfg.tracking.run_name, cfg.seed)
    key = command_key(cfg)
    if not cfg.resume:
        done = finished_attempts(client, cfg, key)
        if done:
            return Continuation(cfg, key, [], finished=done)
        cfg = continue_earlier_attempt(client, cfg, key, run_dataset)
    if OmegaConf.is_list(cfg.resume):  # several runs, continued together as one population
        cfg, members = load_population(client, cfg, overrides)
        return Continuation(cfg, key, members)
    if cfg.resume:  # the run's own config, plus the overrides allowed on resume
        cfg, start = load_run(client, cfg, overrides)
        if cfg.get("dataset"):
            check_same_data(client, cfg, run_dataset(cfg))
        return Continuation(cfg, key, [(cfg, start)])
    k = cfg.population
    members = [cfg] if k == 1 else [member_config(cfg, i) for i in range(k)]
    return Continuation(cfg, key, [(member, None) for member in members])


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


def command_key(cfg: DictConfig) -> str:
    """What identifies "the same command" of a plain run: a digest of the composed config, less
    :data:`RESUME_OVERRIDABLE` and :data:`NOT_THE_COMMAND` (``tracking.run_name`` counts)."""
    settings = flatten(OmegaConf.to_container(cfg, resolve=True))
    kept = {
        key: value
        for key, value in settings.items()
        if key not in RESUME_OVERRIDABLE
        and key != "tracking.run_name"
        and not any(key == p or (p.endswith(".") and key.startswith(p)) for p in NOT_THE_COMMAND)
    }
    kept["tracking.run_name"] = settings.get("tracking.run_name")
    text = json.dumps(kept, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def load_run(client, cfg: DictConfig, overrides, run_id: str | None = None):
    """The run's stored config (with the allowed new overrides) and its last checkpoint."""
    run_id = str(cfg.resume) if run_id is None else run_id
    if in_training_here(cfg.work_dir, run_id):
        raise ConfigError(
            f"resume={run_id} is not allowed now: a process of this machine is training the run; "
            "wait for it to end, or stop it there"
        )
    start = last_checkpoint(client, cfg, run_id)
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
    _fill_hyperparameters_declared_since(stored.algo, run_id)
    stored.tracking = cfg.tracking
    # a sweep job's trial and key are the current attempt's (a retried trial has a new number)
    # (a study's population job: each member keyed by its own seed)
    stored.trial, stored.job_key = cfg.trial, job_key_of_seed(cfg.get("job_key"), stored.seed)
    stored.resume = run_id
    return stored, start


def _fill_hyperparameters_declared_since(algo: DictConfig, run_id: str) -> None:
    """A hyperparameter declared after the run was made (PPO's ``num_envs``, say) takes its
    declared default, which is the behaviour the run had before it existed; logged, so that
    the resumed run says what it was not told."""
    added = declared_since(algo)
    for key, value in added.items():
        algo[key] = value
    if added:
        listed = ", ".join(f"algo.{k}={v!r}" for k, v in added.items())
        log.info("run %s predates %s: resumed with the declared default", run_id, listed)


def load_population(client, cfg: DictConfig, overrides):
    """``resume=[id,...]``: runs of one configuration (a population's members, typically)
    continued together as one population. Returns the population's config and, per member,
    its stored config and last checkpoint."""
    run_ids = [str(run_id) for run_id in cfg.resume]
    listed = f"resume=[{','.join(run_ids)}]"
    if len(run_ids) < 2 or len(set(run_ids)) < len(run_ids):
        raise ConfigError(
            f"{listed}: a list resumes two or more different runs together as a "
            "population; pass a single run id to resume one run"
        )
    members = [load_run(client, cfg, overrides, run_id) for run_id in run_ids]

    def shared_settings(member_cfg: DictConfig) -> dict:
        settings = flatten(OmegaConf.to_container(member_cfg, resolve=True))
        return {k: v for k, v in settings.items() if k not in ("seed", "resume", "job_key")}

    (first_cfg, first_start), first = members[0], shared_settings(members[0][0])
    for run_id, (member_cfg, start) in zip(run_ids[1:], members[1:], strict=True):
        other = shared_settings(member_cfg)
        differing = differing_keys([first, other])
        if differing:
            key = differing[0]
            raise ConfigError(
                f"{listed}: runs {run_ids[0]} and {run_id} differ in {key} "
                f"({first.get(key)!r} vs {other.get(key)!r}); only runs of one configuration "
                "(seeds aside) continue together: resume the others alone"
            )
        for counter, here, there in (
            ("step", first_start.step, start.step),
            ("num_updates", first_start.num_updates, start.num_updates),
        ):
            if there != here:
                raise ConfigError(
                    f"{listed}: run {run_ids[0]} is at {counter} {here} and run {run_id} at "
                    f"{counter} {there}; only runs at the same step and update continue "
                    "together: resume them one by one"
                )
    population = first_cfg.copy()
    population.population = len(members)
    population.resume, population.job_key = run_ids, cfg.get("job_key")
    return population, members


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


# --- the same command run again ---------------------------------------------------------------
def _identity(cfg: DictConfig, key: str) -> tuple[str, list[str]]:
    """The tag that tells this command's runs, and its value for each run it makes: a job's key
    (one per member of a population, the same for all unless it holds ``{seed}``), or for a
    plain command its :func:`command_key`, the same for every member."""
    if cfg.job_key:
        return tracking.JOB_KEY_TAG, run_job_keys(cfg)
    return COMMAND_KEY_TAG, [key] * cfg.population


def _attempts(client, cfg: DictConfig, key: str) -> list:
    """The runs earlier attempts of this command left, any status."""
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        return []
    tag, keys = _identity(cfg, key)
    runs = []
    for value in dict.fromkeys(keys):
        query = tracking.tags_equal({tag: value})
        runs += tracking.search_runs(client, experiment.experiment_id, query)
    return runs


def finished_attempts(client, cfg: DictConfig, key: str) -> list | None:
    """The FINISHED run of each of this command's runs (one, or one per member of a population),
    if earlier attempts finished them all; else None. A member's run is the single run of its
    seed, so a population whose seeds all finished alone has nothing left to train either.
    Said in one line, with what to do instead."""
    tag, keys = _identity(cfg, key)
    finished = [r for r in _attempts(client, cfg, key) if r.info.status == tracking.FINISHED]
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
    log.warning(
        "%s ran before as run(s) %s (%s): continuing it from its last checkpoint",
        what,
        ", ".join(ids),
        earlier[0].info.status,
    )
    cfg = cfg.copy()
    cfg.resume = ids[0] if cfg.population == 1 else [r.info.run_id for r in runs]
    return cfg


def check_same_data(client, cfg: DictConfig, data: RunDataset) -> None:
    """A resumed offline run reloads its dataset by name; refuse, in one line, a dataset rebuilt
    under that name since the run started (other episodes, or another CPU's rounding): the run
    would go on learning from other data. (A job run again does not get here: its earlier run
    is superseded instead, :func:`_why_not_continued`.)"""
    recorded = client.get_run(str(cfg.resume)).data.params
    difference = other_data(recorded, data.params)
    if difference:
        raise ConfigError(
            f"resume={cfg.resume} is not allowed: dataset={data.dataset.id!r} is not the data "
            f"the run learned from ({difference}): a rebuild under its name; restore that "
            "build, or train a new run"
        )


def last_checkpoint(client, cfg: DictConfig, run_id: str) -> Checkpoint:
    """Run ``run_id``'s ``last.pt`` (a clear error if ``tracking.uri`` has no such run):
    the local resume copy (replay buffer included) where this machine trained the run and
    MLflow's is not newer, else the one uploaded to MLflow."""
    tracking.require_run(client, run_id, cfg.tracking.uri, key="resume")
    return run_last_checkpoint(client, cfg.work_dir, run_id)


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
        steps = {run_last_checkpoint(client, cfg.work_dir, run_id).step for run_id in ids}
    if len(steps) > 1:
        return f"whose members' checkpoints are at different steps {sorted(steps)}"
    return None
