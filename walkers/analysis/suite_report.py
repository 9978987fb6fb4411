"""``walkers.compare envs=[...]`` and ``walkers.compare datasets=[...]``: each member's own report,
then the suite's: normalized scores, aggregates with stratified-bootstrap CIs, P(A > B) over the
members, per-member tests corrected by Holm's method, a performance profile and
sample-efficiency curves (:mod:`walkers.analysis.suite` has the definitions).

A suite of envs asks "is A better than B across robots?" (scores normalized on each env's
``scores.random`` and ``scores.reference``); a suite of datasets asks it of offline algorithms
across the datasets of one env, D4RL's table (scores normalized on the references the offline runs
were scored on, with the data's own score beside them)."""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from walkers import CONF_DIR  # noqa: E402
from walkers.analysis import formatting, stats  # noqa: E402
from walkers.analysis.comparison import build_comparison, compare, publish, runs_place  # noqa: E402
from walkers.analysis.formatting import header, interval, one_decimal  # noqa: E402
from walkers.analysis.results import AXIS_NAMES, AlgoResult, Comparison  # noqa: E402
from walkers.errors import ConfigError  # noqa: E402
from walkers.metrics import normalized_score  # noqa: E402
from walkers.tracking.names import ENV_STEPS, GRADIENT_STEPS  # noqa: E402


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
        built[dataset] = (comparison, client, one, _dataset_task(dataset, offline))
    for dataset, (comparison, client, one, _) in built.items():  # every dataset was found
        publish(comparison, client, one, Path(cfg.out) / dataset.replace("/", "_"))
    comparisons = {dataset: comparison for dataset, (comparison, *_) in built.items()}
    tasks = {dataset: task for dataset, (*_, task) in built.items()}
    out = Path(cfg.out) / "datasets"
    return write_suite(comparisons, tasks, cfg, out, kind="dataset"), out


def _dataset_task(name: str, offline: list[AlgoResult]) -> Task:
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


def write_suite(comparisons, tasks: dict[str, Task], cfg: DictConfig, out: Path, kind: str) -> str:
    out.mkdir(parents=True, exist_ok=True)
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
    alpha = 1 - cfg.confidence
    improvement = {
        f"{a} vs {b}": stats.average_improvement(scores[a], scores[b], **boot) for a, b in pairs
    }
    what = (
        "per env (`conf/env/*.yaml` scores)"
        if kind == "env"
        else f"on the references the offline runs of {cfg.env.id} were scored on"
    )
    lines = [
        f"# Suite: {', '.join(tasks)}",
        "",
        f"Normalized score = 100 x (score - random) / (reference - random), {what}; score: "
        f"`{cfg.score}`. Aggregates over ({kind}, seed) follow rliable (Agarwal et al. 2021); "
        f"CIs are stratified bootstraps (seeds resampled within each {kind}), "
        f"{cfg.confidence:.0%}.",
        "",
        *_budget_lines(results),
        *header(kind, ["random", "reference"] + (["the data's own"] if kind == "dataset" else [])),
    ]
    for t in tasks.values():
        own = f" {t.own:.1f} |" if kind == "dataset" and t.own is not None else ""
        lines.append(f"| {t.name} | {t.random:g} | {t.reference:g} |" + own)
    lines += [
        "",
        "## Aggregates (normalized)",
        "",
        *header("arm", [*stats.AGGREGATES, "runs", "CPU-hours, runs summed"]),
    ]
    for arm, agg in aggregates.items():
        cells = [interval(*v, written=one_decimal) for v in agg.values()]
        runs = sum(len(x) for x in scores[arm].values())
        lines.append(
            f"| {arm} | "
            + " | ".join(cells)
            + f" | {runs} | {formatting.cpu_hours(*_cpu_hours(results[arm]), digits='.2f')} |"
        )
    lines += [
        "",
        f"## Per {kind} (normalized IQM [CI])",
        "",
        *header("arm", tasks),
    ]
    for arm in scores:
        lines.append(
            f"| {arm} | "
            + " | ".join(interval(*per_task[arm][t], written=one_decimal) for t in tasks)
            + " |"
        )
    if kind == "dataset":
        own = [f"{t.own:.1f}" if t.own is not None else "-" for t in tasks.values()]
        lines.append("| the data's own | " + " | ".join(own) + " |")
    lines += _per_target_lines(results, tasks)
    lines += [
        "",
        "## Pairs",
        "",
        f"P(A > B) averaged over {kind}s; per-{kind} Mann-Whitney p, corrected for "
        f"{len(raw_p)} tests by {correction} (a difference needs adjusted p < {alpha:.2g}).",
        "",
        *header("pair", [f"P(A > B) over {kind}s", kind, "p", "Holm-adjusted p", "verdict"]),
    ]
    for a, b in pairs:
        p, lo, hi = improvement[f"{a} vs {b}"]
        for t in tasks:
            key = f"{a} vs {b} on {t}"
            verdict = "no reliable difference"
            if adjusted[key] < alpha:  # the side the rank test found, not the means'
                verdict = f"{a if stats.a_ranks_higher(scores[a][t], scores[b][t]) else b} better"
            lines.append(
                f"| {a} vs {b} | {p:.2f} [{lo:.2f}, {hi:.2f}] | {t} | {raw_p[key]:.4f} "
                f"| {adjusted[key]:.4f} | {verdict} |"
            )
    lines += [
        "",
        "![performance profile](performance_profile.png)",
        "![sample efficiency](sample_efficiency.png)",
        "",
        f"The sample-efficiency band is the IQM's {cfg.confidence:.0%} stratified bootstrap CI.",
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))
    axis = AXIS_NAMES[ENV_STEPS if kind == "env" else GRADIENT_STEPS]
    _plots(scores, curves, out, axis, cfg.confidence)
    summary = {
        f"{kind}s": {
            t.name: {"random": t.random, "reference": t.reference}
            | ({"own": t.own} if kind == "dataset" else {})
            for t in tasks.values()
        },
        "aggregates": aggregates,
        f"per_{kind}": per_task,
        "probability_of_improvement": improvement,
        "p_values": raw_p,
        "holm_adjusted": adjusted,
        "correction": correction,
        "budgets": {arm: _budget(by_task) for arm, by_task in results.items()},
        "cpu_hours": {arm: _cpu_hours(by_task) for arm, by_task in results.items()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    best = max(aggregates, key=lambda arm: aggregates[arm]["IQM"][0])
    top = aggregates[best]["IQM"][0]
    return f"suite of {len(tasks)} {kind}s: the highest normalized IQM is {best}'s ({top:.1f})"


def _budget(by_task: dict[str, AlgoResult]) -> int | None:
    """An arm's budget when it is the same on every member, else None."""
    budgets = {r.budget for r in by_task.values()}
    return budgets.pop() if len(budgets) == 1 else None


def _budget_lines(results: dict[str, dict[str, AlgoResult]]) -> list[str]:
    """Each arm's budget, on its x-axis (offline arms are compared each at its own)."""
    parts = []
    for arm, by_task in results.items():
        budget, axis = _budget(by_task), next(iter(by_task.values())).x_axis
        shown = f"{budget:,}" if budget is not None else "varies"
        parts.append(f"{arm} {shown} {AXIS_NAMES[axis]}")
    return [f"Budgets: {'; '.join(parts)}.", ""]


def _cpu_hours(by_task: dict[str, AlgoResult]) -> tuple[float, int, int]:
    """An arm's CPU-hours over the suite: (hours, runs that counted them, runs)."""
    counted = [r.cpu_hours for r in by_task.values()]
    runs = sum(len(r.runs) for r in by_task.values())
    return sum(h for h, _ in counted), sum(n for _, n in counted), runs


def _per_target_lines(results, tasks: dict[str, Task]) -> list[str]:
    """Return-conditioned arms (DT): the normalized IQM [CI] at each target return, per task."""
    lines = []
    for arm, by_task in results.items():
        targets = sorted(
            {t for r in by_task.values() for t in r.per_target}, key=float, reverse=True
        )
        if len(targets) < 2:
            continue
        lines += [
            "",
            f"## {arm} per target return (normalized IQM [CI])",
            "",
            *header("target", tasks),
        ]
        for target in targets:
            cells = []
            for name, task in tasks.items():
                found = by_task[name].per_target.get(target)
                if found is None:
                    cells.append("-")
                    continue
                point, low, high = (float(task.normalize(v)) for v in found)
                cells.append(
                    interval(point, min(low, high), max(low, high), written=one_decimal)
                )  # the map may reverse
            lines.append(f"| {float(target):g} | " + " | ".join(cells) + " |")
    return lines


def _plots(scores, curves, out: Path, axis: str, confidence: float) -> None:
    taus = np.linspace(-10, 150, 161)
    fig, ax = plt.subplots(figsize=(6, 4))
    for arm, per_task in scores.items():
        ax.plot(
            taus,
            stats.performance_profile(per_task, taus),
            label=arm,
        )
    ax.set(
        xlabel="normalized score tau", ylabel="fraction of runs > tau", title="Performance profile"
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "performance_profile.png", dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    for arm, per_task in curves.items():
        last = min(steps[-1] for runs in per_task.values() for steps, _ in runs)
        grid = np.linspace(0, last, 50)
        point, low, high = stats.iqm_curve(per_task, grid, confidence=confidence)
        ax.plot(grid, point, label=arm)
        ax.fill_between(grid, low, high, alpha=0.2)
    ax.set(
        xlabel=axis,
        ylabel="IQM normalized eval return",
        title=f"Sample efficiency ({confidence:.0%} CI)",
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "sample_efficiency.png", dpi=100)
    plt.close(fig)
