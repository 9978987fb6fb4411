"""How a named run continues: ``resume=<id>`` (``resume=[<id>,...]`` for a population's runs
together), with the run's stored config and the overrides allowed on resume (:func:`resumed`),
from its last checkpoint (the local resume copy or MLflow's, the newer:
:func:`walkers.training.run.last_checkpoint`);
an offline run goes on learning from the data it started on (:func:`check_same_data`).

The same command run again finds the run to continue in :mod:`walkers.training.attempts`; the
run itself is reopened by :meth:`TrainingRun.open` (``cfg.resume`` set), and the book goes on
from the checkpoint found here (:meth:`RunBook.continue_from`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from omegaconf import DictConfig, OmegaConf

from walkers.agents.declarations.schemas import declared_since
from walkers.errors import ConfigError
from walkers.tracking.client import flatten, require_run
from walkers.tracking.names import differing_keys
from walkers.training.checkpoints import Checkpoint
from walkers.training.provenance import (
    job_key_of_seed,
    other_data,
)
from walkers.training.run import in_training_here, last_checkpoint
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


def load_run(client, cfg: DictConfig, overrides, run_id: str | None = None):
    """The run's stored config (with the allowed new overrides) and its last checkpoint."""
    run_id = str(cfg.resume) if run_id is None else run_id
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


def resumed(
    client, cfg: DictConfig, overrides, run_dataset: Callable[[DictConfig], RunDataset]
) -> tuple[DictConfig, list[tuple[DictConfig, Checkpoint]]]:
    """``resume=`` (one run, or several continued together as a population): the config to
    train (the stored one, with the overrides it takes) and, per run, its config and last
    checkpoint. ``run_dataset`` loads an offline run's data (once a session)."""
    if OmegaConf.is_list(cfg.resume):
        return load_population(client, cfg, overrides)
    cfg, start = load_run(client, cfg, overrides)
    if cfg.get("dataset"):  # an offline run goes on learning from the data it started on
        check_same_data(client, cfg, run_dataset(cfg))
    return cfg, [(cfg, start)]
