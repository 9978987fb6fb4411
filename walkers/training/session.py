"""One training session from a composed config: check it, resume or open the run(s), build the
envs and the agent, run the loop, end every run with its status; return the optimized metric.

    single run:   envs + agent -> TrainingRun.open -> RunBook -> train_online | _offline | _sb3
                  (an agent declaring several_envs, num_envs > 1: a vector env -> train_vectorized)
    population:   K members' envs + one agent -> K TrainingRuns and books -> train_population

Every run opened is ended by :func:`walkers.training.run.ending`, whatever way the session ends.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from walkers import tracking
from walkers.agents.factory import build_agent
from walkers.errors import ConfigError
from walkers.seeding import eval_start_seeds
from walkers.training import resume
from walkers.training.bookkeeping import RunBook
from walkers.training.envs import env_spaces, make_env, make_vector_env, steps_in_workers
from walkers.training.evaluation import (
    PopulationEvaluation,
    offline_evaluation,
    offline_references,
    with_normalized_score,
)
from walkers.training.loops import (
    train_offline,
    train_online,
    train_population,
    train_sb3,
    train_vectorized,
)
from walkers.training.provenance import MEMBER_TAG, POPULATION_TAG, shareable
from walkers.training.run import (
    ENV_STEP_AXIS,
    GRADIENT_STEP_AXIS,
    SEED_IN_KEY,
    TrainingRun,
    ending,
    job_key_of_seed,
)
from walkers.training.settings import RunSettings
from walkers.training.validate import check_environment, is_offline, validate

log = logging.getLogger("walkers")


#: What a run's evaluations report to, given the run's final config: ``(step, eval mean) ->
#: stop?`` (an Optuna trial's reporter, made by walkers.train above this package), or None.
EvaluationReporter = Callable[[DictConfig], Callable[[int, float], bool] | None]


def train(
    cfg: DictConfig,
    overrides: list[str] | tuple = (),
    tags: dict | None = None,
    reporter: EvaluationReporter | None = None,
) -> float:
    """Train as ``cfg`` says; ``overrides`` are the command-line overrides (used by resume);
    ``tags`` go on the run(s), new or resumed (a multirun job's place in its multirun);
    ``reporter`` makes what a single run's evaluations report to (a sweep's trial)."""
    resume.check_resume_given(cfg.resume)
    check_environment(cfg)  # before anything is created
    if cfg.population == 1:  # the key and name of the one run: its seed's, as a member's
        cfg.job_key = job_key_of_seed(cfg.job_key, cfg.seed)
        cfg.tracking.run_name = job_key_of_seed(cfg.tracking.run_name, cfg.seed)
    if not cfg.resume:
        validate(cfg)  # before anything is created
        warn_short_warmup(cfg)
    client = tracking.connect(cfg.tracking.uri)
    if not cfg.resume:
        done = resume.finished_attempts(client, cfg)
        if done:  # a job run again after it finished: its result, nothing trained
            ids = ", ".join(run.info.run_id for run in done)
            log.info("job %s already FINISHED as run(s) %s: nothing to train", cfg.job_key, ids)
            values = [run.data.metrics.get(cfg.optimized_metric, math.nan) for run in done]
            return float(np.mean(values))
        # a multirun job run again (its worker died) continues its earlier attempt's run
        cfg = resume.continue_earlier_attempt(client, cfg)
    state, members = None, None
    if OmegaConf.is_list(cfg.resume):  # several runs, continued together as one population
        cfg, members = resume.load_population(client, cfg, overrides)
        validate(cfg)
    elif cfg.resume:  # the run's own config, plus the overrides allowed on resume
        cfg, state = resume.load_run(client, cfg, overrides)
        validate(cfg)
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    if cfg.population > 1:
        summaries = _train_population(cfg, client, members, tags or {})
        values = [s.get(cfg.optimized_metric, math.nan) for s in summaries]
        log.info("%s per member = %s", cfg.optimized_metric, values)
        return float(np.mean(values))
    summary = _train_single(cfg, client, state, tags or {}, reporter)
    value = summary.get(cfg.optimized_metric, math.nan)
    log.info("%s = %s", cfg.optimized_metric, value)
    return value


def _train_single(
    cfg: DictConfig, client, state: dict | None, tags: dict, reporter: EvaluationReporter | None
) -> dict[str, float]:
    data = load_dataset(cfg) if is_offline(cfg) else None
    if data is not None and cfg.resume:
        resume.check_same_data(client, cfg, data)
    eval_env = make_env(cfg.env, shaping=False)
    env = video_env = None
    try:
        agent = build_agent(
            cfg, env_spaces(eval_env), **({"dataset": data} if data is not None else {})
        )
        # the training env(s), as the agent declares it learns (offline: none)
        several_envs = agent.several_envs and agent.num_envs > 1
        if not agent.offline:
            env = (
                make_vector_env(cfg.env, agent.num_envs, workers=_workers(cfg, agent.num_envs))
                if several_envs
                else make_env(cfg.env)
            )
        if cfg.video_every:
            video_env = make_env(cfg.env, shaping=False, render_mode="rgb_array")
        if agent.trains_itself:
            agent.attach(env, cfg.total_steps)  # SB3's model is built on its training env
        axis = GRADIENT_STEP_AXIS if data is not None else ENV_STEP_AXIS
        references = offline_references(cfg.env, data) if data is not None else None
        runs = [TrainingRun.open(client, cfg, axis, data, extra_tags=tags)]
        # From here on the run exists in MLflow: every way out sets its final status.
        with ending(runs):
            options = (
                {
                    "evaluation": offline_evaluation(agent, references.normalized),
                    "summarize": with_normalized_score(references.normalized),
                }
                if data is not None
                else {}
            )
            if reporter is not None:  # e.g. a job of an Optuna study: its pruner
                options["on_evaluation"] = reporter(cfg)
            book = _book(cfg, runs[0], agent, env, eval_env, axis, video_env, **options)
            if state is not None:
                resume.restore(book, state)
                log.info("resuming run %s at step %d", runs[0].run_id, book.progress.step)
            if agent.offline:
                summary = train_offline(agent, book)
            elif agent.trains_itself:
                summary = train_sb3(agent, book)
            elif several_envs:
                summary = train_vectorized(agent, env, book)
            else:
                summary = train_online(agent, env, book)
            if book.stopped_early:
                runs[0].mark_pruned(book.progress.step)
            return summary
    finally:
        for e in (env, eval_env, video_env):
            if e is not None:
                e.close()


def _train_population(
    cfg: DictConfig, client, resumed: list[tuple[DictConfig, dict]] | None, tags: dict
) -> list[dict[str, float]]:
    """``population=K``: K members in one agent and one loop, one MLflow run per member.

    ``resumed``: per member, the stored config and last checkpoint of a run to continue.
    """
    k = cfg.population
    members = (
        [member_config(cfg, i) for i in range(k)] if resumed is None else [m for m, _ in resumed]
    )
    envs, eval_envs, runs = None, [], []
    try:
        # member i's env is env i of one vector env
        envs = make_vector_env(cfg.env, k, step_info=False, workers=_workers(cfg, k))
        eval_envs = [make_env(cfg.env, shaping=False) for _ in members]
        agent = build_agent(cfg, env_spaces(eval_envs[0]), population=k)
        # the members' evaluations play together, each from its own seed's start states
        evaluation = PopulationEvaluation(
            agent, eval_envs, [eval_start_seeds(m.seed, m.eval_episodes) for m in members]
        )
        with ending(runs, population=True):
            for i, member in enumerate(members):
                place = {POPULATION_TAG: str(k), MEMBER_TAG: str(i)}
                runs.append(
                    TrainingRun.open(client, member, ENV_STEP_AXIS, extra_tags=tags | place)
                )
            books = [
                _book(
                    member,
                    run,
                    agent.member_policy(i),
                    envs,
                    eval_envs[i],
                    evaluation=evaluation.of_member(i),
                    env_member=i,
                )
                for i, (member, run) in enumerate(zip(members, runs, strict=True))
            ]
            for book, (_, state) in zip(books, resumed or [], strict=False):
                resume.restore(book, state)
            if resumed:
                log.info("resuming %d runs together at step %d", k, books[0].progress.step)
            return train_population(agent, envs, books)
    finally:
        for e in [envs, *eval_envs]:
            if e is not None:
                e.close()


def _book(cfg: DictConfig, run, agent, env, eval_env, axis=ENV_STEP_AXIS, video_env=None, **kw):
    """The run's :class:`RunBook`, with its config in every checkpoint."""
    return RunBook(
        agent,
        env,
        eval_env,
        run,
        RunSettings.of(cfg),
        cfg.env.threshold,
        checkpoint_extra={"config": shareable(cfg)},
        video_env=video_env,
        axis=axis,
        **kw,
    )


def _workers(cfg: DictConfig, num_envs: int) -> bool:
    """Whether the run's ``num_envs`` training envs step in worker processes (``vector_env``)."""
    return steps_in_workers(cfg.get("vector_env", "auto"), num_envs)


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


def load_dataset(cfg: DictConfig):
    """The offline dataset ``cfg.dataset``, checked against ``cfg.env``."""
    from walkers.data import datasets  # Minari is imported only when a dataset is used

    data = datasets.load(cfg.dataset)
    if data.env_id is not None and data.env_id != cfg.env.id:
        raise ConfigError(
            f"dataset={data.id!r} was recorded on {data.env_id}, not on env.id={cfg.env.id!r}: "
            f"pass the env it was recorded on"
        )
    return data


def warn_short_warmup(cfg: DictConfig) -> None:
    """A learning-rate warm-up longer than the run never reaches ``algo.lr`` (algo=dt)."""
    warmup = OmegaConf.select(cfg, "algo.warmup_steps")
    if warmup and warmup > cfg.total_steps:
        log.warning(
            "algo.warmup_steps=%d is more than total_steps=%d: the learning rate ends at %.0f%% "
            "of algo.lr=%g; lower algo.warmup_steps (e.g. to total_steps / 10)",
            warmup,
            cfg.total_steps,
            100 * cfg.total_steps / warmup,
            cfg.algo.lr,
        )
