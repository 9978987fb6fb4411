"""How a run continues: every way training picks up where a run left off, in one module.

- ``resume=<id>`` (``resume=[<id>,...]`` for a population's runs together): the run's stored
  config with the overrides allowed on resume (:func:`load_run`, :func:`load_population`);
- a job run again (its ``job_key``): FINISHED runs are its result (:func:`finished_attempts`),
  a RUNNING, KILLED or FAILED one continues (:func:`continue_earlier_attempt`);
- which checkpoint: the local resume copy or MLflow's, the newer (:func:`last_checkpoint`);
- an offline run goes on learning from the data it started on (:func:`check_same_data`);
- into the run: agent, progress, RNGs and the agent's resume notes (:func:`restore`).

The run itself is reopened by :meth:`TrainingRun.open` (``cfg.resume`` set), and the checkpoints
read here are written by :meth:`RunBook.save_checkpoint`.
"""

from __future__ import annotations

import logging
import math

from omegaconf import DictConfig, OmegaConf

from walkers import tracking
from walkers.agents.declarations.schemas import declared_since
from walkers.errors import CheckpointError, ConfigError
from walkers.seeding import restore_torch_rng
from walkers.tracking import differing_keys, flatten
from walkers.training import checkpoints
from walkers.training.bookkeeping import Progress, RunBook
from walkers.training.provenance import (
    DIVERGED_TAG,
    MEMBER_TAG,
    SUPERSEDED_TAG,
    dataset_params,
    other_data,
)
from walkers.training.run import RunFolder, TrainingRun, job_key_of_seed, run_job_keys

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


def check_resume_given(resume) -> None:
    """``resume=`` with nothing after it (``resume=$RUN_ID`` with the variable unset) is a
    mistake, never a request for a fresh run."""
    empty = resume is not None and (
        (isinstance(resume, str) and not resume.strip())
        or (OmegaConf.is_list(resume) and len(resume) == 0)
    )
    if empty:
        raise ConfigError(
            f"resume={resume!r} is empty: pass the MLflow run id to continue (resume=<run id>, "
            "or resume=[<id>,<id>] for a population), or leave resume out to start a new run"
        )


def load_run(client, cfg: DictConfig, overrides, run_id: str | None = None):
    """The run's stored config (with the allowed new overrides) and its last checkpoint."""
    run_id = str(cfg.resume) if run_id is None else run_id
    state = last_checkpoint(client, cfg, run_id)
    stored = OmegaConf.create(state["config"])
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
    return stored, state


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

    (first_cfg, first_state), first = members[0], shared_settings(members[0][0])
    for run_id, (member_cfg, state) in zip(run_ids[1:], members[1:], strict=True):
        other = shared_settings(member_cfg)
        differing = differing_keys([first, other])
        if differing:
            key = differing[0]
            raise ConfigError(
                f"{listed}: runs {run_ids[0]} and {run_id} differ in {key} "
                f"({first.get(key)!r} vs {other.get(key)!r}); only runs of one configuration "
                "(seeds aside) continue together: resume the others alone"
            )
        for counter, of in (("step", "trainer"), ("num_updates", "agent")):
            if state[of][counter] != first_state[of][counter]:
                raise ConfigError(
                    f"{listed}: run {run_ids[0]} is at {counter} {first_state[of][counter]} and "
                    f"run {run_id} at {counter} {state[of][counter]}; only runs at the same step "
                    "and update continue together: resume them one by one"
                )
    population = first_cfg.copy()
    population.population = len(members)
    population.resume, population.job_key = run_ids, cfg.get("job_key")
    return population, members


# --- a job run again -------------------------------------------------------------------------
def _attempts(client, cfg: DictConfig) -> list:
    """The runs earlier attempts of this job (``job_key``) left, any status."""
    if not cfg.job_key:
        return []
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        return []
    runs = []
    for key in dict.fromkeys(run_job_keys(cfg)):  # one key, or a key per member
        query = tracking.tags_equal({tracking.JOB_KEY_TAG: key})
        runs += tracking.search_runs(client, experiment.experiment_id, query)
    return runs


def finished_attempts(client, cfg: DictConfig) -> list | None:
    """The FINISHED run of each of this job's runs (one, or one per member of a population),
    if earlier attempts finished them all; else None. A member's run is the single run of its
    seed, so a population whose seeds all finished alone has nothing left to train either."""
    keys = run_job_keys(cfg)
    finished = [r for r in _attempts(client, cfg) if r.info.status == tracking.FINISHED]
    shared_key = len(set(keys)) < len(keys)  # no {seed} in it: members told apart by their tag
    done = []
    for member, key in enumerate(keys):
        runs = [
            r
            for r in finished
            if r.data.tags.get(tracking.JOB_KEY_TAG) == key
            and (not shared_key or r.data.tags.get(MEMBER_TAG) == str(member))
        ]
        if not runs:
            return None
        done.append(runs[0])
    return done


def continue_earlier_attempt(client, cfg: DictConfig) -> DictConfig:
    """A job run again continues the run(s) of its earlier attempt instead of starting more.

    Ray runs a job again when its worker died (kill -9, ``ray stop`` on the node); a study
    runs a trial again when its sweeper died (``optuna.max_retry``). The earlier attempt's
    run, left RUNNING (or KILLED by SIGTERM), is found by the job's key (``job_key``) and
    resumed from its last checkpoint, fetched from MLflow on whatever worker this is; a
    population's K member runs are resumed together (``resume=[...]``). A run that ended
    FAILED (an error, not a divergence) is continued the same way, as a rerun of an A/B
    study asks. Without checkpoints to continue from (none yet, or a population's members
    cut at different steps) the earlier runs are marked FAILED (tagged superseded) and new
    ones start.
    """
    earlier = [
        r
        for r in _attempts(client, cfg)
        if r.info.status in ("RUNNING", "KILLED")
        or (r.info.status == "FAILED" and not _gave_up_on(r))
    ]
    if not earlier:
        return cfg
    if cfg.population > 1:
        by_member = {int(r.data.tags.get(MEMBER_TAG, -1)): r for r in earlier}
        runs = [by_member.get(i) for i in range(cfg.population)]
    else:
        runs = earlier[:1]
    problem = _why_not_continued(client, cfg, runs)
    ids = [r.info.run_id for r in earlier if r is not None]
    if problem:
        log.warning(
            "job %s ran before as run(s) %s, %s: marked FAILED; starting anew",
            cfg.job_key,
            ", ".join(ids),
            problem,
        )
        for run_id in ids:
            run = TrainingRun.attach(client, cfg.work_dir, run_id)
            run.set_tags({SUPERSEDED_TAG: f"{problem}: the job ran again as new run(s)"})
            run.end(tracking.FAILED)
        return cfg
    log.warning(
        "job %s ran before as run(s) %s (%s): continuing it from its last checkpoint",
        cfg.job_key,
        ", ".join(ids),
        earlier[0].info.status,
    )
    cfg = cfg.copy()
    cfg.resume = ids[0] if cfg.population == 1 else [r.info.run_id for r in runs]
    return cfg


def check_same_data(client, cfg: DictConfig, data) -> None:
    """A resumed offline run reloads its dataset by name; refuse, in one line, a dataset rebuilt
    under that name since the run started (other episodes, or another CPU's rounding): the run
    would go on learning from other data. (A job run again does not get here: its earlier run
    is superseded instead, :func:`_why_not_continued`.)"""
    recorded = client.get_run(str(cfg.resume)).data.params
    difference = other_data(recorded, dataset_params(data, cfg.env))
    if difference:
        raise ConfigError(
            f"resume={cfg.resume} is not allowed: dataset={data.id!r} is not the data the run "
            f"learned from ({difference}): a rebuild under its name; restore that build, or "
            "train a new run"
        )


def last_checkpoint(client, cfg: DictConfig, run_id: str) -> dict:
    """Run ``run_id``'s ``last.pt`` (a clear error if ``tracking.uri`` has no such run):
    the local resume copy (replay buffer included) where this machine trained the run and
    MLflow's is not newer, else the one uploaded to MLflow."""
    tracking.require_run(client, run_id, cfg.tracking.uri, key="resume")
    return _last_checkpoint(client, run_id, cfg.work_dir)


# --- its last checkpoint, and into the run --------------------------------------------------
def _last_checkpoint(client, run_id: str, work_dir) -> dict:
    folder = RunFolder.of(work_dir, run_id)
    local = folder.resume_checkpoint
    try:
        uploaded = tracking.download_checkpoint(client, run_id, "last.pt", folder.download)
    except CheckpointError:  # never uploaded (e.g. the store was down): the local copy will do
        if not local.is_file():
            raise
        uploaded = None
    uploaded = checkpoints.load(uploaded) if uploaded is not None else None  # damaged: an error
    if local.is_file():
        whole = checkpoints.load(local)
        if uploaded is None or whole["trainer"]["step"] >= uploaded["trainer"]["step"]:
            log.info("resuming from %s (with its replay buffer, if the agent has one)", local)
            return whole
        log.warning(
            "%s is at step %d, MLflow's last.pt at step %d: resuming from MLflow's",
            local,
            whole["trainer"]["step"],
            uploaded["trainer"]["step"],
        )
    return uploaded


def _gave_up_on(run) -> bool:
    """A FAILED run not to continue: superseded by a new attempt, or ended by divergence."""
    return SUPERSEDED_TAG in run.data.tags or DIVERGED_TAG in run.data.tags


def _why_not_continued(client, cfg: DictConfig, runs: list) -> str | None:
    """Why the earlier attempt's runs (one per member, None where missing) cannot go on."""
    if any(r is None for r in runs):
        return f"which are not the {cfg.population} members of a population"
    if cfg.get("dataset"):  # an offline job: its dataset may have been rebuilt since
        from walkers.data import datasets  # Minari is imported only when a dataset is used

        now = dataset_params(datasets.load(cfg.dataset), cfg.env)
        difference = other_data(runs[0].data.params, now)
        if difference:
            return f"which learned from another build of dataset={cfg.dataset} ({difference})"
    steps = set()
    for run in runs:
        run_id = run.info.run_id
        uploaded = [a.path for a in client.list_artifacts(run_id, "checkpoints")]
        local = RunFolder.of(cfg.work_dir, run_id).resume_checkpoint
        if "checkpoints/last.pt" not in uploaded and not local.is_file():
            return "which ended without a checkpoint"
        if len(runs) > 1:  # members continue together only from one step
            steps.add(_last_checkpoint(client, run_id, cfg.work_dir)["trainer"]["step"])
    if len(steps) > 1:
        return f"whose members' checkpoints are at different steps {sorted(steps)}"
    return None


def restore(book: RunBook, state: dict) -> None:
    """Continue the book's run from ``state``, a checkpoint written by
    :meth:`RunBook.save_checkpoint`: the agent, the loop's progress, torch's RNGs, the training
    env's RNG (taken at the book's first reset), and the agent's resume notes as run tags."""
    book.agent.load_state_dict(state["agent"])
    # a checkpoint from before runs counted their CPU time: the total is unknown, not 0
    book.progress = Progress(**{"cpu_seconds": math.nan} | state["trainer"])
    book.last_checkpoint_step = book.progress.step
    restore_torch_rng(state)
    book.pending_env_rng = state.get("env_rng")
    mark = book.run.logged_through
    if mark is not None and mark > book.progress.step:
        log.warning(
            "run %s logged metrics up to step %d before it stopped; it resumes from its "
            "checkpoint at step %d and logs from step %d on (no step is logged twice)",
            book.run.run_id,
            mark,
            book.progress.step,
            mark + 1,
        )
    if notes := book.agent.resume_notes():  # e.g. a replay buffer that had to be refilled
        if refill := notes.get("walkers.buffer_refill"):
            log.warning(
                "run %s resumed without the replay buffer's transitions: refilling them, "
                "%s, before updating again",
                book.run.run_id,
                refill,
            )
        book.run.set_tags(notes)
