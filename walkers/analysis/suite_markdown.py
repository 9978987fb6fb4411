"""A suite report's markdown (``report.md``), written from its :class:`SuiteStatistics`."""

from __future__ import annotations

from omegaconf import DictConfig

from walkers.analysis import formatting, stats
from walkers.analysis.comparison_data import AXIS_NAMES, AlgoResult
from walkers.analysis.formatting import header, interval, one_decimal
from walkers.analysis.suite_scores import SuiteStatistics, Task, budget, suite_cpu_hours


def suite_markdown(s: SuiteStatistics, tasks: dict[str, Task], cfg: DictConfig, kind: str) -> str:
    """The report's text."""
    scores, results, aggregates, per_task = s.scores, s.results, s.aggregates, s.per_task
    pairs, raw_p, adjusted, improvement = s.pairs, s.raw_p, s.adjusted, s.improvement
    correction, alpha = s.correction, 1 - cfg.confidence
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
            + f" | {runs} | {formatting.cpu_hours(*suite_cpu_hours(results[arm]), digits='.2f')} |"
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
    return "\n".join(lines)


def _budget_lines(results: dict[str, dict[str, AlgoResult]]) -> list[str]:
    """Each arm's budget, on its x-axis (offline arms are compared each at its own)."""
    parts = []
    for arm, by_task in results.items():
        steps, axis = budget(by_task), next(iter(by_task.values())).x_axis
        shown = f"{steps:,}" if steps is not None else "varies"
        parts.append(f"{arm} {shown} {AXIS_NAMES[axis]}")
    return [f"Budgets: {'; '.join(parts)}.", ""]


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
