"""Which finished runs a comparison takes: the env's, FINISHED, one budget per x-axis, not
pruned, with their logged eval curves; every run left out gets a note for the report. Also the
env's published reference figures for the algorithms compared."""

from __future__ import annotations

import re
from collections import Counter

import numpy as np

from walkers import tracking
from walkers.analysis import stats
from walkers.analysis.results import AXIS_NAMES, SeedRun
from walkers.tracking import ENV_STEPS, GRADIENT_STEPS, KIND_TAG

CURVE_METRIC = "eval/return_mean"
TARGET_METRIC = re.compile(r"eval/target_(.+)/return_mean")  # a DT's return at one target


def x_axis(run) -> str:
    return run.data.tags.get(tracking.X_AXIS_TAG, ENV_STEPS)


def _budget(run) -> int | None:
    value = run.data.params.get("total_steps")
    return int(value) if value is not None and value.isdigit() else None


def _runs(n: int) -> str:
    return f"{n} run" if n == 1 else f"{n} runs"


def _most_common(values) -> object:
    return Counter(values).most_common(1)[0][0]


def _listed(counts: Counter, key: str) -> str:
    return ", ".join(f"{key}={value}: {n}" for value, n in sorted(counts.items(), key=str))


def select_runs(
    runs: list,
    env_id: str,
    algos: list[str],
    budget: int | None,
    gradient_budget: int | None = None,
    dataset: str | None = None,
):
    """The comparable training runs of ``algos`` on ``env_id``, and notes on the rest.

    Returns ``(chosen runs, budgets, notes)``: ``budgets`` maps each x-axis to the budget its runs
    share, the given one (``budget`` for env steps, ``gradient_budget`` for offline runs) or else
    the most common among the finished runs. Offline runs also share one dataset (``dataset``, or
    the most common).
    """
    notes: list[str] = []
    training = [r for r in runs if r.data.tags.get(KIND_TAG, "train") == "train"]
    wanted = [r for r in training if not algos or r.data.tags.get("algo") in algos]
    other_envs = Counter(r.data.tags.get("env") for r in wanted if r.data.tags.get("env") != env_id)
    if other_envs:
        listed = ", ".join(f"{env}: {n}" for env, n in sorted(other_envs.items(), key=str))
        notes.append(f"{_runs(sum(other_envs.values()))} on other envs ({listed})")
    on_env = [r for r in wanted if r.data.tags.get("env") == env_id]
    unfinished = [r for r in on_env if r.info.status != tracking.FINISHED]
    for r in unfinished:
        notes.append(
            f"run {r.info.run_id} ({r.data.tags.get('algo')}, seed {r.data.tags.get('seed')}) "
            f"is {r.info.status}"
        )
    pruned = [r for r in on_env if tracking.PRUNED_TAG in r.data.tags]
    if pruned:
        notes.append(f"{_runs(len(pruned))} of sweep trials stopped early by pruning")
    finished = [
        r
        for r in on_env
        if r.info.status == tracking.FINISHED and tracking.PRUNED_TAG not in r.data.tags
    ]
    offline = [r for r in finished if x_axis(r) == GRADIENT_STEPS]
    if offline:
        dataset = dataset or _most_common(r.data.tags.get("dataset") for r in offline)
        other = Counter(r.data.tags.get("dataset") for r in offline)
        del other[dataset]
        if other:
            notes.append(
                f"{_runs(sum(other.values()))} trained on another dataset than {dataset} "
                f"({_listed(other, 'dataset')})"
            )
        finished = [
            r for r in finished if x_axis(r) == ENV_STEPS or r.data.tags.get("dataset") == dataset
        ]
    chosen, budgets = [], {}
    for axis, given in ((ENV_STEPS, budget), (GRADIENT_STEPS, gradient_budget)):
        on_axis = [r for r in finished if x_axis(r) == axis]
        if not on_axis:
            continue
        budgets[axis] = given if given is not None else _most_common(_budget(r) for r in on_axis)
        other = Counter(_budget(r) for r in on_axis if _budget(r) != budgets[axis])
        if other:
            notes.append(
                f"{_runs(sum(other.values()))} with another budget than {budgets[axis]} "
                f"{AXIS_NAMES[axis]} ({_listed(other, 'total_steps')})"
            )
        chosen += [r for r in on_axis if _budget(r) == budgets[axis]]
    return chosen, budgets, notes


def load_seed_runs(client, runs: list, threshold: float) -> dict[str, SeedRun]:
    """Eval curves and summaries of ``runs`` by run id (runs without evals are not in it)."""
    loaded: dict[str, SeedRun] = {}
    for run in runs:
        steps, values = tracking.metric_history(client, run.info.run_id, CURVE_METRIC)
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
