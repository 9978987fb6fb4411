"""``walkers.compare envs=[...]`` and ``walkers.compare datasets=[...]``: each member's own report,
then the suite's: normalized scores, aggregates with stratified-bootstrap CIs, P(A > B) over the
members, per-member tests corrected by Holm's method, a performance profile and
sample-efficiency curves: the scores and statistics are :mod:`walkers.analysis.suite_scores`'
(the definitions :mod:`walkers.analysis.stats`'), the text :mod:`walkers.analysis.suite_markdown`'s,
the plots :func:`walkers.analysis.plots.suite_plots`.

A suite of envs asks "is A better than B across robots?" (scores normalized on each env's
``scores.random`` and ``scores.reference``); a suite of datasets asks it of offline algorithms
across the datasets of one env, D4RL's table (scores normalized on the references the offline runs
were scored on, with the data's own score beside them)."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from walkers.analysis.comparison import build_comparison, compare, publish, runs_place
from walkers.analysis.comparison_data import AXIS_NAMES
from walkers.analysis.plots import suite_plots
from walkers.analysis.suite_markdown import suite_markdown
from walkers.analysis.suite_scores import (
    Task,
    budget,
    dataset_task,
    env_config,
    suite_cpu_hours,
    suite_statistics,
)
from walkers.errors import ConfigError
from walkers.tracking.names import ENV_STEPS, GRADIENT_STEPS


def compare_suite(cfg: DictConfig, beside: dict | None = None) -> tuple[str, Path]:
    """Each env's comparison and report, then the suite's report; returns its verdict and dir."""
    if len(cfg.envs) < 2:
        raise ConfigError(f"envs={list(cfg.envs)} is not allowed: two or more conf/env names")
    if cfg.datasets:
        raise ConfigError("envs= and datasets= are not allowed together: a suite is of one kind")
    envs = {name: env_config(name) for name in cfg.envs}
    comparisons, tasks = {}, {}
    for name, env in envs.items():
        one = cfg.copy()
        one.env = env
        one.out = str(Path(cfg.out).parent / env.id)
        comparisons[name] = compare(one, beside)[0]
        tasks[name] = Task(name, env.scores.random, env.scores.reference)
    out = Path(cfg.out).parent / "suite"
    return write_suite(comparisons, tasks, cfg, out, kind="env"), out


def compare_datasets(cfg: DictConfig) -> tuple[str, Path]:
    """Each dataset's comparison and report (``<out>/<dataset>/``), then the suite's over the
    offline arms (``<out>/datasets/``); returns its verdict and dir."""
    names = list(cfg.datasets) if OmegaConf.is_list(cfg.datasets) else None
    if names is None or len(names) < 2 or len(set(names)) < len(names):
        shown = names if names is not None else repr(cfg.datasets)
        raise ConfigError(
            f"datasets={shown} is not allowed: two or more different datasets of "
            f"env={cfg.env.id}, as a list: [a,b]"
        )
    built = {}
    for name in names:
        one = cfg.copy()
        one.dataset = name
        one.datasets = []
        comparison, client = build_comparison(one)
        offline = [r for r in comparison.algos if r.x_axis == GRADIENT_STEPS]
        if not offline:
            raise ConfigError(
                f"datasets: {name!r} has no finished offline runs of {cfg.env.id} in "
                f"{runs_place(cfg)}"
            )
        dataset = offline[0].dataset  # the name as recorded: with its version
        if dataset in built:
            raise ConfigError(f"datasets={names} is not allowed: {dataset} is named twice")
        built[dataset] = (comparison, client, one, dataset_task(dataset, offline))
    for dataset, (comparison, client, one, _) in built.items():  # every dataset was found
        publish(comparison, client, one, Path(cfg.out) / dataset.replace("/", "_"))
    comparisons = {dataset: comparison for dataset, (comparison, *_) in built.items()}
    tasks = {dataset: task for dataset, (*_, task) in built.items()}
    out = Path(cfg.out) / "datasets"
    return write_suite(comparisons, tasks, cfg, out, kind="dataset"), out


def write_suite(comparisons, tasks: dict[str, Task], cfg: DictConfig, out: Path, kind: str) -> str:
    """The suite's report (``report.md``, its plots, ``summary.json``) into ``out``; returns
    its verdict."""
    out.mkdir(parents=True, exist_ok=True)
    s = suite_statistics(comparisons, tasks, cfg, kind)
    (out / "report.md").write_text(suite_markdown(s, tasks, cfg, kind))
    axis = AXIS_NAMES[ENV_STEPS if kind == "env" else GRADIENT_STEPS]
    suite_plots(s.scores, s.curves, out, axis, cfg.confidence)
    summary = {
        f"{kind}s": {
            t.name: {"random": t.random, "reference": t.reference}
            | ({"own": t.own} if kind == "dataset" else {})
            for t in tasks.values()
        },
        "aggregates": s.aggregates,
        f"per_{kind}": s.per_task,
        "probability_of_improvement": s.improvement,
        "p_values": s.raw_p,
        "holm_adjusted": s.adjusted,
        "correction": s.correction,
        "budgets": {arm: budget(by_task) for arm, by_task in s.results.items()},
        "cpu_hours": {arm: suite_cpu_hours(by_task) for arm, by_task in s.results.items()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    best = max(s.aggregates, key=lambda arm: s.aggregates[arm]["IQM"][0])
    top = s.aggregates[best]["IQM"][0]
    return f"suite of {len(tasks)} {kind}s: the highest normalized IQM is {best}'s ({top:.1f})"
