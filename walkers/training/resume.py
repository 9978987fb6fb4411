"""``resume=``: continue a run (or a population's runs together) from its last checkpoint.

A resumed run uses its stored config; only :data:`RESUME_OVERRIDABLE` keys are taken from the
new command line. Its last checkpoint comes from :meth:`TrainingRun.last_checkpoint`.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from walkers.errors import ConfigError
from walkers.tracking import differing_keys, flatten
from walkers.training.run import TrainingRun, job_key_of_seed

#: Keys a resumed run takes from the new command line; everything else comes from its checkpoint.
RESUME_OVERRIDABLE = (
    "total_steps",
    "device",
    "torch_threads",
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
    state = TrainingRun.last_checkpoint(client, cfg, run_id)
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
    stored.tracking = cfg.tracking
    # a sweep job's trial and key are the current attempt's (a retried trial has a new number)
    # (a study's population job: each member keyed by its own seed)
    stored.trial, stored.job_key = cfg.trial, job_key_of_seed(cfg.get("job_key"), stored.seed)
    stored.resume = run_id
    return stored, state


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
