"""Which finished runs a comparison takes: the env's, FINISHED, one budget per x-axis, not
pruned, with their logged eval curves; every run left out gets a note for the report. Also the
env's published reference figures for the algorithms compared."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Mapping

import numpy as np

from walkers.analysis import formatting, stats
from walkers.analysis.comparison_data import AXIS_NAMES, SeedRun
from walkers.errors import ConfigError
from walkers.tracking.client import metric_history
from walkers.tracking.names import (
    ENV_STEPS,
    FINISHED,
    GRADIENT_STEPS,
    KIND_TAG,
    ORIGIN_TAG,
    PRUNED_TAG,
    X_AXIS_TAG,
    total_steps_of,
)
from walkers.training.provenance import DATA_DIGEST, DATA_STATS_KEYS, other_data

CURVE_METRIC = "eval/return_mean"
TARGET_METRIC = re.compile(r"eval/target_(.+)/return_mean")  # a DT's return at one target


def x_axis(run) -> str:
    return run.data.tags.get(X_AXIS_TAG, ENV_STEPS)


def _budget(run) -> int | None:
    value = total_steps_of(run)
    return int(value) if value is not None and value.isdigit() else None


def _most_common(values) -> object:
    return Counter(values).most_common(1)[0][0]


def _listed(counts: Counter, key: str) -> str:
    return ", ".join(f"{key}={value}: {n}" for value, n in sorted(counts.items(), key=str))


def comparable_runs(
    runs: list,
    env_id: str,
    algos: list[str],
    budget: int | None,
    gradient_budget: int | Mapping[str, int] | None = None,
    dataset: str | None = None,
):
    """The comparable training runs of ``algos`` on ``env_id``, and notes on the rest.

    Returns ``(chosen runs, budgets, notes)``: ``budgets`` maps each x-axis to the budget its runs
    share, the given one (``budget`` for env steps) or else the most common among the finished
    runs. Offline algorithms are each compared at their own budget, as their papers train them
    (TD3+BC for 1M gradient steps, DT for 100k): ``gradient_budget`` (one for all, or one per
    algorithm), else each algorithm's most common; ``budgets[GRADIENT_STEPS]`` is that budget
    when they share one, else a mapping algorithm -> budget. Offline runs also share one dataset
    (``dataset``, or the most common).
    """
    notes: list[str] = []
    training = [r for r in runs if r.data.tags.get(KIND_TAG, "train") == "train"]
    wanted = [r for r in training if not algos or r.data.tags.get("algo") in algos]
    other_envs = Counter(r.data.tags.get("env") for r in wanted if r.data.tags.get("env") != env_id)
    if other_envs:
        listed = ", ".join(f"{env}: {n}" for env, n in sorted(other_envs.items(), key=str))
        notes.append(f"{formatting.runs(sum(other_envs.values()))} on other envs ({listed})")
    on_env = [r for r in wanted if r.data.tags.get("env") == env_id]
    unfinished = [r for r in on_env if r.info.status != FINISHED]
    for r in unfinished:
        notes.append(
            f"run {r.info.run_id} ({r.data.tags.get('algo')}, seed {r.data.tags.get('seed')}) "
            f"is {r.info.status}"
        )
    pruned = [r for r in on_env if PRUNED_TAG in r.data.tags]
    if pruned:
        notes.append(f"{formatting.runs(len(pruned))} of sweep trials stopped early by pruning")
    finished = [r for r in on_env if r.info.status == FINISHED and PRUNED_TAG not in r.data.tags]
    offline = [r for r in finished if x_axis(r) == GRADIENT_STEPS]
    if offline:
        dataset = resolve_dataset(dataset, offline, env_id)
        other = Counter(r.data.tags.get("dataset") for r in offline)
        del other[dataset]
        if other:
            notes.append(
                f"{formatting.runs(sum(other.values()))} trained on another dataset than {dataset} "
                f"({_listed(other, 'dataset')})"
            )
        finished = [
            r for r in finished if x_axis(r) == ENV_STEPS or r.data.tags.get("dataset") == dataset
        ]
    chosen, budgets = [], {}
    on_env_steps = [r for r in finished if x_axis(r) == ENV_STEPS]
    if on_env_steps:
        budgets[ENV_STEPS], kept = _one_budget(on_env_steps, budget, ENV_STEPS, notes)
        chosen += kept
    offline_by_algo: dict[str, list] = {}
    for r in finished:
        if x_axis(r) == GRADIENT_STEPS:
            offline_by_algo.setdefault(r.data.tags.get("algo"), []).append(r)
    offline_budgets = {}
    for algo, algo_runs in sorted(offline_by_algo.items()):
        given = gradient_budget
        if isinstance(gradient_budget, Mapping):
            given = gradient_budget.get(algo)
        offline_budgets[algo], kept = _one_budget(algo_runs, given, GRADIENT_STEPS, notes, algo)
        chosen += kept
    if offline_budgets:
        check_one_build(dataset, [r for r in chosen if x_axis(r) == GRADIENT_STEPS])
        shared = set(offline_budgets.values())
        budgets[GRADIENT_STEPS] = shared.pop() if len(shared) == 1 else offline_budgets
    return chosen, budgets, notes


def resolve_dataset(wanted: str | None, offline: list, env_id: str) -> str:
    """The dataset the offline runs are compared on: ``wanted`` (``-v<N>`` may be left off when
    one version has runs), else the one most of them learned from."""
    found = Counter(r.data.tags.get("dataset") for r in offline)
    if wanted is None:
        return _most_common(found.elements())
    if wanted in found:
        return wanted
    versions = [d for d in found if re.fullmatch(re.escape(wanted) + r"-v\d+", str(d))]
    if len(versions) == 1:
        return versions[0]
    if versions:
        raise ConfigError(
            f"dataset={wanted!r} is not allowed: runs learned from several versions of it "
            f"({', '.join(sorted(versions))}); name one"
        )
    raise ConfigError(
        f"dataset={wanted!r} is not allowed: no finished offline run of {env_id} learned from it; "
        f"datasets they learned from: {', '.join(sorted(map(str, found)))}"
    )


def _build_text(run) -> str:
    params = run.data.params
    episodes, steps, mean = (params.get(key, "?") for key in DATA_STATS_KEYS[:3])
    digest = params.get(DATA_DIGEST)
    return f"{episodes} episodes, {steps} steps, return {mean}" + (
        f", digest {digest}" if digest else ""
    )


def check_one_build(dataset: str, runs: list) -> None:
    """Refuse, in one line, offline runs of ``dataset`` that learned from different data under its
    name (a rebuild by other runs, or on another CPU): their scores answer different questions.
    Each build is the first run's of its kind; a run is of it when
    :func:`~walkers.training.provenance.other_data` finds no difference (digests where both
    have one, the recorded statistics otherwise)."""
    builds: list[tuple[object, list]] = []  # (the first run of a build, its runs), first seen first
    for run in sorted(runs, key=lambda r: r.info.start_time or 0):
        for first, members in builds:
            ours, theirs = run.data.params, first.data.params
            if not other_data(ours, theirs) and not other_data(theirs, ours):
                members.append(run)
                break
        else:
            builds.append((run, [run]))
    if len(builds) < 2:
        return
    listed = "; ".join(
        f"{_build_text(first)}: "
        + ", ".join(f"{a} {n}" for a, n in sorted(Counter(_algo_of(r) for r in members).items()))
        for first, members in builds
    )
    raise ConfigError(
        f"dataset={dataset!r} is not one dataset here: its runs learned from {len(builds)} builds "
        f"of it ({listed}); compare the runs of one build (another experiment: "
        "walkers.ingest into=..., or tracking.experiment= for the new runs)"
    )


def _algo_of(run) -> str:
    return str(run.data.tags.get("algo", "?"))


def _one_budget(runs: list, given: int | None, axis: str, notes: list[str], algo: str = ""):
    """The budget ``runs`` are compared at (``given``, or their most common) and the runs that
    have it; a note names the rest."""
    chosen = given if given is not None else _most_common(_budget(r) for r in runs)
    other = Counter(_budget(r) for r in runs if _budget(r) != chosen)
    if other:
        whose = f" of {algo}" if algo else ""
        notes.append(
            f"{formatting.runs(sum(other.values()))}{whose} with another budget than {chosen} "
            f"{AXIS_NAMES[axis]} ({_listed(other, 'total_steps')})"
        )
    return chosen, [r for r in runs if _budget(r) == chosen]


def load_seed_runs(client, runs: list, threshold: float) -> dict[str, SeedRun]:
    """Eval curves and summaries of ``runs`` by run id (runs without evals are not in it)."""
    loaded: dict[str, SeedRun] = {}
    for run in runs:
        steps, values = metric_history(client, run.info.run_id, CURVE_METRIC)
        if not steps:
            continue
        loaded[run.info.run_id] = SeedRun(
            run_id=run.info.run_id,
            algo=run.data.tags["algo"],
            seed=run.data.tags.get("seed", "?"),
            steps=np.asarray(steps),
            returns=np.asarray(values),
            summary=stats.run_summary(steps, values, threshold),
            x_axis=x_axis(run),
            dataset=run.data.tags.get("dataset"),
            normalized_score=run.data.metrics.get("final/normalized_score"),
            references=_references(run.data.params),
            behaviour_return=_float(run.data.params.get("dataset_stats.behaviour_return")),
            cpu_hours=run.data.metrics.get("final/cpu_hours"),
            final_per_target=final_per_target(run.data.metrics),
            budget=_budget(run),
            origin=run.data.tags.get(ORIGIN_TAG),
        )
    return loaded


def final_per_target(metrics: dict[str, float]) -> dict[str, float]:
    """A return-conditioned run's last evaluation at each of its target returns (the run's
    latest metric values are its last evaluation's)."""
    return {
        match.group(1): value
        for key, value in metrics.items()
        if (match := TARGET_METRIC.fullmatch(key))
    }


def _float(value: str | None) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):  # absent, or "None"
        return None


def _references(params: dict) -> tuple[float, float, str] | None:
    """An offline run's normalized-score references (random, expert, source), if it logged them."""
    random, expert = (_float(params.get(f"normalized_score.{k}")) for k in ("random", "expert"))
    if random is None or expert is None:
        return None
    return random, expert, params.get("normalized_score.references", "dataset")


def published_figures(env_cfg, algorithms: list[str]) -> list[dict]:
    """The env's published reference figures (``published:`` in its config) for ``algorithms``,
    in their order."""
    figures = [dict(f) for f in (env_cfg.get("published") or [])]
    return [f for a in algorithms for f in figures if f.get("algo") == a]
