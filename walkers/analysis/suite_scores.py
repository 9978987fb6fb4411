"""A suite's scores and statistics: its members (an env, or a dataset of one env: a :class:`Task`)
and the returns each normalizes between, each arm's normalized scores and curves on every
member, and the statistics of :mod:`walkers.analysis.stats` over them (:func:`suite_statistics`)."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig, OmegaConf

from walkers import CONF_DIR
from walkers.analysis import stats
from walkers.analysis.comparison_data import AlgoResult, Comparison
from walkers.errors import ConfigError
from walkers.metrics import normalized_score
from walkers.tracking.names import GRADIENT_STEPS


@dataclass(frozen=True)
class Task:
    """One member of a suite (an env, or a dataset of one env) and the two returns its scores
    are normalized between; ``own``: the data's own normalized score (datasets)."""

    name: str
    random: float
    reference: float
    own: float | None = None

    def normalize(self, x) -> np.ndarray:
        return normalized_score(np.asarray(x, dtype=float), self.random, self.reference)


def env_config(name: str) -> DictConfig:
    path = CONF_DIR / "env" / f"{name}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in (CONF_DIR / "env").glob("*.yaml")))
        raise ConfigError(f"envs: {name!r} is not allowed: must be one of {known}")
    env = OmegaConf.load(path)
    scores = env.get("scores") or {}
    if scores.get("random") is None or scores.get("reference") is None:
        raise ConfigError(
            f"envs: {name!r} has no scores.random and scores.reference in conf/env/{name}.yaml: "
            "a suite report normalizes every env's scores with them"
        )
    return env


def dataset_task(name: str, offline: list[AlgoResult]) -> Task:
    """A dataset as a suite member: the references its offline runs were scored on."""
    first = offline[0]
    refs = first.runs[0].references
    if refs is None or refs[0] == refs[1]:
        raise ConfigError(
            f"datasets: {name!r}'s runs have no reference returns to normalize on (set "
            "scores.random and scores.expert in conf/env, or record the dataset's references)"
        )
    return Task(name, refs[0], refs[1], own=first.normalized(first.runs[0].behaviour_return))


def _arms_of(comparison: Comparison, kind: str) -> list[AlgoResult]:
    """The arms a suite aggregates: every arm across envs, the offline ones across datasets."""
    return [r for r in comparison.algos if kind == "env" or r.x_axis == GRADIENT_STEPS]


def _normalized(comparisons, tasks, kind: str) -> tuple[dict, dict, dict]:
    """arm -> task -> normalized seed scores, arm -> task -> normalized eval curves, and
    arm -> task -> its AlgoResult, for the arms that ran on every task."""
    scores, curves, results = {}, {}, {}
    for name, comparison in comparisons.items():
        task = tasks[name]
        for r in _arms_of(comparison, kind):
            scores.setdefault(r.algo, {})[name] = task.normalize(r.scores)
            curves.setdefault(r.algo, {})[name] = [
                (run.steps, task.normalize(run.returns)) for run in r.runs
            ]
            results.setdefault(r.algo, {})[name] = r
    keep = [a for a in scores if len(scores[a]) == len(comparisons)]
    return (
        {a: scores[a] for a in keep},
        {a: curves[a] for a in keep},
        {a: results[a] for a in keep},
    )


@dataclass(frozen=True)
class SuiteStatistics:
    """What a suite report says, computed: per arm, its normalized scores and curves per task
    and its runs (``results``); the aggregates with CIs; the IQM per task; per pair, P(A > B)
    over tasks and per task the Mann-Whitney p, raw and Holm-adjusted."""

    scores: dict
    curves: dict
    results: dict
    aggregates: dict
    per_task: dict
    pairs: list
    raw_p: dict
    adjusted: dict
    improvement: dict
    correction: str


def suite_statistics(comparisons, tasks: dict[str, Task], cfg: DictConfig, kind: str):
    """The suite's :class:`SuiteStatistics` (``cfg``: the bootstrap's settings)."""
    boot = {
        "confidence": cfg.confidence,
        "n_resamples": min(cfg.n_resamples, 2000),
        "seed": cfg.seed,
    }
    scores, curves, results = _normalized(comparisons, tasks, kind)
    if len(scores) < 1:
        raise ConfigError(f"no arm ran on every {kind} of {list(tasks)}: nothing to aggregate")
    correction = f"Holm's step-down method over every pair on every {kind}"
    aggregates = {arm: stats.aggregate_cis(per_task, **boot) for arm, per_task in scores.items()}
    per_task = {
        arm: {t: stats.aggregate_cis({t: x}, **boot)["IQM"] for t, x in by_task.items()}
        for arm, by_task in scores.items()
    }
    pairs = list(itertools.combinations(scores, 2))
    raw_p = {
        f"{a} vs {b} on {t}": stats.mann_whitney_p(scores[a][t], scores[b][t])
        for a, b in pairs
        for t in tasks
    }
    adjusted = stats.holm(raw_p)
    improvement = {
        f"{a} vs {b}": stats.average_improvement(scores[a], scores[b], **boot) for a, b in pairs
    }
    return SuiteStatistics(
        scores, curves, results, aggregates, per_task, pairs, raw_p, adjusted, improvement,
        correction,
    )  # fmt: skip


def budget(by_task: dict[str, AlgoResult]) -> int | None:
    """An arm's budget when it is the same on every member, else None."""
    budgets = {r.budget for r in by_task.values()}
    return budgets.pop() if len(budgets) == 1 else None


def suite_cpu_hours(by_task: dict[str, AlgoResult]) -> tuple[float, int, int]:
    """An arm's CPU-hours over the suite: (hours, runs that counted them, runs)."""
    counted = [r.cpu_hours for r in by_task.values()]
    runs = sum(len(r.runs) for r in by_task.values())
    return math.fsum(h for h, _ in counted), sum(n for _, n in counted), runs
