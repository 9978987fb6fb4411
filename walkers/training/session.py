"""One training session from a composed config, in three steps: plan, build, run.

    plan    walkers.training.command_plan.plan_command: what the command will do (new runs, runs
            to continue and from which checkpoints, or nothing: they finished), the config
            checked once
    build   the data, the envs, the agent, the MLflow run(s), their books (:func:`build`)
    run     the loop that fits (:func:`run_loop`), then every run ends with its status

    single run:   envs + agent -> TrainingRun.open -> RunBook -> train_online | _offline | _sb3
                  (an agent declaring several_envs, num_envs > 1: a vector env -> train_vectorized)
    population:   K members' envs + one agent -> K TrainingRuns and books -> train_population

Every run opened is ended by :func:`walkers.training.run.ending_and_saying_how`, whatever way
the session ends; every env made is closed.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from contextlib import ExitStack

import numpy as np
import torch
from omegaconf import DictConfig

from walkers.agents.factory import build_agent
from walkers.seeding import eval_start_seeds
from walkers.training.bookkeeping import (
    PopulationEvaluation,
    RunBook,
    offline_evaluation,
    with_normalized_score,
)
from walkers.training.command_plan import Plan, plan_command
from walkers.training.envs import env_spaces, make_env, make_vector_env
from walkers.training.loops import (
    train_offline,
    train_online,
    train_population,
    train_sb3,
    train_vectorized,
)
from walkers.training.provenance import MEMBER_TAG, POPULATION_TAG
from walkers.training.run import (
    ENV_STEP_AXIS,
    GRADIENT_STEP_AXIS,
    TrainingRun,
    ending_and_saying_how,
)

log = logging.getLogger("walkers")


#: What a run's evaluations report to, given the run's final config: ``(step, eval mean) ->
#: stop?`` (an Optuna trial's reporter, made by walkers.train above this package), or None.
EvaluationReporter = Callable[[DictConfig], Callable[[int, float], bool] | None]


def run_training(
    cfg: DictConfig,
    overrides: list[str] | tuple = (),
    tags: dict | None = None,
    reporter: EvaluationReporter | None = None,
) -> float:
    """Train as ``cfg`` says; ``overrides`` are the command-line overrides (used by resume);
    ``tags`` go on the run(s), new or resumed (a multirun job's place in its multirun);
    ``reporter`` makes what a single run's evaluations report to (a sweep's trial)."""
    work = plan_command(cfg, overrides)
    if work.finished:  # said by the plan; the runs' result, nothing trained
        return work.finished_value()
    if work.cfg.torch_threads:
        torch.set_num_threads(work.cfg.torch_threads)
    with ExitStack() as closing:
        agent, env, books = build(work, closing, tags or {}, reporter)
        summaries = run_loop(agent, env, books)
    values = [s.get(work.cfg.optimized_metric, math.nan) for s in summaries]
    if len(values) > 1:
        log.info("%s per member = %s", work.cfg.optimized_metric, values)
    else:
        log.info("%s = %s", work.cfg.optimized_metric, values[0])
    return float(np.mean(values))


def run_loop(agent, env, books: list[RunBook]) -> list[dict[str, float]]:
    """Run the loop that fits the agent and its books (one per run); each run's summary."""
    if len(books) > 1:
        return train_population(agent, env, books)
    book = books[0]
    if agent.offline:
        summary = train_offline(agent, book)
    elif agent.trains_itself:
        summary = train_sb3(agent, book)
    elif agent.several_envs and agent.num_envs > 1:
        summary = train_vectorized(agent, env, book)
    else:
        summary = train_online(agent, env, book)
    if book.stopped_early:
        book.run.mark_pruned(book.progress.step)
    return [summary]


def build(work: Plan, closing: ExitStack, tags: dict, reporter: EvaluationReporter | None) -> tuple:
    """The agent, its training env(s) (closed by ``closing``; None: an offline run) and one book
    per run (each run ended by ``closing``, whatever way the session ends), as ``work`` plans
    them."""
    if work.cfg.population > 1:
        return _build_population(work, closing, tags)
    return _build_single(work, closing, tags, reporter)


def _build_single(
    work: Plan, closing: ExitStack, tags: dict, reporter: EvaluationReporter | None
) -> tuple:
    cfg, data = work.cfg, work.data
    eval_env = _closed_by(closing, make_env(cfg.env, shaping=False))
    agent = build_agent(
        cfg, env_spaces(eval_env), **({"dataset": data.dataset} if data is not None else {})
    )
    env = video_env = None  # the training env(s), as the agent declares it learns (offline: none)
    if not agent.offline:
        several = agent.several_envs and agent.num_envs > 1
        env = _closed_by(
            closing,
            make_vector_env(cfg.env, agent.num_envs, vector_env=cfg.get("vector_env", "auto"))
            if several
            else make_env(cfg.env),
        )
    if cfg.video_every:
        video_env = _closed_by(closing, make_env(cfg.env, shaping=False, render_mode="rgb_array"))
    if agent.trains_itself:
        agent.attach(env, cfg.total_steps)  # SB3's model is built on its training env
    axis = GRADIENT_STEP_AXIS if data is not None else ENV_STEP_AXIS
    runs = []
    closing.enter_context(
        ending_and_saying_how(runs)
    )  # from here on every run opened ends with a status
    continues = work.continues[0]
    tags = tags if continues else tags | work.new_run_tags
    runs.append(TrainingRun.open(work.client, cfg, axis, continues, data, extra_tags=tags))
    options = {}
    if data is not None:
        normalized = data.references.normalized
        options["evaluation"] = offline_evaluation(agent, normalized)
        options["summarize"] = with_normalized_score(normalized)
    if reporter is not None:  # e.g. a job of an Optuna study: its pruner
        options["on_evaluation"] = reporter(cfg)
    book = RunBook(agent, runs[0], env, eval_env, video_env, start=work.starts[0], **options)
    if continues:
        log.info("resuming run %s at step %d", continues, book.progress.step)
    return agent, env, [book]


def _build_population(work: Plan, closing: ExitStack, tags: dict) -> tuple:
    """``population=K``: K members in one agent and one loop, one MLflow run per member."""
    cfg, k = work.cfg, work.cfg.population
    # member i's env is env i of one vector env
    envs = _closed_by(
        closing,
        make_vector_env(cfg.env, k, step_info=False, vector_env=cfg.get("vector_env", "auto")),
    )
    eval_envs = [_closed_by(closing, make_env(cfg.env, shaping=False)) for _ in range(k)]
    agent = build_agent(cfg, env_spaces(eval_envs[0]), population=k)
    # the members' evaluations play together, each from its own seed's start states
    evaluation = PopulationEvaluation(
        agent, eval_envs, [eval_start_seeds(m.seed, m.eval_episodes) for m in work.members]
    )
    runs = []
    closing.enter_context(ending_and_saying_how(runs, population=True))
    for i, (member, continues) in enumerate(zip(work.members, work.continues, strict=True)):
        place = {POPULATION_TAG: str(k), MEMBER_TAG: str(i)}
        new = {} if continues else work.new_run_tags
        runs.append(
            TrainingRun.open(
                work.client, member, ENV_STEP_AXIS, continues, extra_tags=tags | place | new
            )
        )
    books = [
        RunBook(
            agent.member_policy(i),
            run,
            envs,
            eval_envs[i],
            env_member=i,
            evaluation=evaluation.of_member(i),
            start=start,
        )
        for i, (run, start) in enumerate(zip(runs, work.starts, strict=True))
    ]
    if work.resumed:
        log.info("resuming %d runs together at step %d", k, books[0].progress.step)
    return agent, envs, books


def _closed_by(closing: ExitStack, env):
    closing.callback(env.close)
    return env
