"""The A/B report: a plain-language verdict, tables, and the plots of
:mod:`walkers.analysis.plots`.

Everything here renders a :class:`walkers.analysis.comparison_data.Comparison`; nothing is
computed that the
comparison does not hold, except the learning-curve bands (a bootstrap over seeds per step).
A ``group_by`` study also gets ``group_by.png``: the score (IQM, CI) against the keys' values.
Published reference figures for the env, when it has any, get a table of their own.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from walkers.analysis import formatting
from walkers.analysis.comparison_data import (
    AXIS_NAMES,
    PUBLISHED_CAVEAT,
    Comparison,
    PairResult,
)
from walkers.analysis.formatting import interval, number
from walkers.analysis.plots import plot_group_by, plot_learning_curves, plot_scores
from walkers.analysis.power import MAX_SEEDS, TARGET
from walkers.tracking.names import ENV_STEPS

QUANTITY_NAMES = {"score": "final return", "auc": "AUC (rate of learning)"}


def _normalized_lines(r, score: str) -> list[str]:
    """An offline arm's normalized score (of the report's ``score``, a return or the mean return
    over the run) beside its raw value, and its behaviour policy's."""
    refs, (point, low, high) = r.runs[0].references, r.normalized_iqm
    if refs is None or point is None:
        if r.normalized_score_mean is None:
            return []
        return [
            "",
            f"{r.algo}: final normalized score {number(r.normalized_score_mean)} (mean over "
            f"seeds; 0 = a random policy, 100 = the behaviour policy of {r.dataset}).",
        ]
    random, expert, source = refs
    scale = (
        f"the env's references (conf/env: random {number(random)}, expert {number(expert)})"
        if source == "env"
        else f"the dataset's (random {number(random)}, behaviour {number(expert)})"
    )
    ci = f" [{number(low)}, {number(high)}]" if low is not None else ""
    line = (
        f"{r.label}: normalized score {number(point)}{ci} (IQM of `{score}`, "
        f"{number(r.iqm[0])}, and its CI, on {scale})"
    )
    if r.runs[0].behaviour_return is not None:
        behaviour = r.runs[0].behaviour_return
        line += (
            f"; the data's behaviour policy: return {number(behaviour)}, "
            f"normalized score {number(r.normalized(behaviour))}"
        )
    return ["", line + "."]


def _per_target_lines(r) -> list[str]:
    """A return-conditioned arm's (DT's) final return at each target it was asked for."""
    if len(r.per_target) < 2:  # one target: the headline above
        return []
    cells = []
    for target, (point, low, high) in r.per_target.items():
        score = r.normalized(point)
        normalized = "" if score is None else f", normalized {number(score)}"
        cells.append(f"asked for {number(float(target))}: {interval(point, low, high)}{normalized}")
    return [
        "",
        f"{r.label} by target return (the IQM of the final returns and its CI): "
        + "; ".join(cells)
        + ".",
    ]


def _steps(x: float | None, axis: str = ENV_STEPS) -> str:
    if x is None or not math.isfinite(x):
        return "not reached"
    return f"{x:,.0f}" if axis == ENV_STEPS else f"{x:,.0f} {AXIS_NAMES[axis]}"


def budgets_text(c: Comparison) -> str:
    """ "10,000 env steps; offline: 2,000 gradient steps on <dataset>" (or "dt 20,000 and td3bc
    100,000 gradient steps" where offline algorithms differ)."""
    parts = []
    for axis, budget in c.budgets.items():
        if isinstance(budget, dict):  # offline algorithms, each at its own budget
            each = " and ".join(f"{algo} {b:,}" for algo, b in budget.items())
            text = f"{each} {AXIS_NAMES[axis]}"
        elif budget:
            text = f"{budget:,} {AXIS_NAMES[axis]}"
        else:
            text = f"their budget in {AXIS_NAMES[axis]}"
        if axis != ENV_STEPS:
            datasets = sorted({r.dataset for r in c.algos if r.x_axis == axis})
            text = f"offline: {text} on dataset {', '.join(map(str, datasets))}"
        parts.append(text)
    return "; ".join(parts) or "their budget"


def _clause(pair: PairResult, confidence: float) -> str:
    """What the evidence says of ``pair``, named from the side it favours (the arms are ordered
    by the final score's IQM, which need not be the side a reliable AUC difference favours)."""
    if pair.decisive(confidence) < 0:
        pair = pair.flipped()
    name = QUANTITY_NAMES[pair.quantity]
    evidence = (
        f"P({pair.a} > {pair.b}) = {interval(*pair.p_improvement)}, "
        f"Mann-Whitney p = {pair.p_value:.2g}"
    )
    power = pair.power
    if power is not None:
        evidence += (
            f", difference {power.difference:+.3g} (Hedges' g {power.effect_size:+.2f}), "
            f"power {power.power:.0%}"
        )
    if pair.decisive(confidence) > 0:
        word = "learns better" if pair.quantity == "score" else "learns faster"
        return f"{pair.a} {word} ({name}: {evidence})"
    clause = f"no reliable difference in {name} ({evidence})"
    if power is None:
        return clause
    if power.precise():
        return (
            f"{clause}: a small effect measured precisely (the study had "
            f"{power.power_for_smallest:.0%} power to detect a difference of {power.smallest:.3g})"
        )
    settle = (
        f"{power.seeds} seeds per arm would detect the observed difference with "
        f"{TARGET:.0%} power" if power.seeds is not None else
        f"not even {MAX_SEEDS} seeds per arm would detect the observed difference"
    )  # fmt: skip
    return (
        f"{clause}: underpowered, not equal (only {power.power_for_smallest:.0%} power to detect "
        f"a difference of {power.smallest:.3g}); {settle} ({power.method})"
    )


def verdict(c: Comparison) -> str:
    """One paragraph: which algorithm learns better and faster, and how sure we can be."""
    level = f"{c.confidence:.0%}"
    ranked = sorted(c.algos, key=lambda r: -r.iqm[0])
    rank = {r.algo: i for i, r in enumerate(ranked)}
    seeds = {r.algo: len(r.runs) for r in c.algos}
    seed_counts = ", ".join(f"{a} {n}" for a, n in seeds.items())
    lines = [
        f"On {c.env_id} ({budgets_text(c)}; seeds: {seed_counts}),"
        f" ranked by the IQM of {c.score}: "
        + ", ".join(f"{r.algo} {interval(*r.iqm)}" for r in ranked)
        + (f" ({level} CIs)." if any(not math.isnan(r.iqm[1]) for r in ranked) else ".")
    ]
    pairs = [p if rank[p.a] < rank[p.b] else p.flipped() for p in c.pairs]
    for a, b in {(p.a, p.b): None for p in pairs}:
        clauses = [_clause(p, c.confidence) for p in pairs if (p.a, p.b) == (a, b)]
        line = f"{a} vs {b}: {'; '.join(clauses)}."
        smallest_p = 2 / math.comb(seeds[a] + seeds[b], seeds[a])
        if smallest_p >= 1 - c.confidence:
            line += (
                f" With {seeds[a]} and {seeds[b]} seeds no difference can reach p < "
                f"{1 - c.confidence:.2g} (the smallest possible p is {smallest_p:.2g}): "
                "run more seeds."
            )
        lines.append(line)
    reached = [f"{r.algo} {r.as_dict()['threshold_reached']}/{len(r.runs)}" for r in c.algos]
    lines.append(f"Seeds reaching the threshold {number(c.threshold)}: {', '.join(reached)}.")
    return " ".join(lines)


def _arms_section(c: Comparison) -> list[str]:
    """How runs became arms: the study's keys, and every group split into several arms."""
    if not (c.group_by or c.splits):
        return []
    how = (
        f"grouped by {', '.join(f'`{k}`' for k in c.group_by)}"
        if c.group_by
        else "grouped by algorithm"
    )
    out = [
        "",
        "## Arms",
        "",
        f"Runs are {how}. An arm is one configuration: runs whose configs differ in anything but "
        "the seed and keys that cannot change results "
        "(`walkers.analysis.arms.NOT_THE_EXPERIMENT`) are separate arms, never pooled.",
    ]
    if c.splits:
        out += ["", "Split into several arms:", ""] + [f"- {note}" for note in c.splits]
    return out


def _pairwise_section(c: Comparison, level: str) -> list[str]:
    """Each pair of arms: P(A > B), the test, the effect and the power."""
    if not c.pairs:  # one arm: nothing to pair
        return []
    out = [
        "",
        "## Pairwise",
        "",
        f"| A vs B | on | P(A > B) [{level} CI] | Mann-Whitney p | mean A - B (Hedges' g) "
        f"| power | seeds per arm for {TARGET:.0%} power | power for the smallest effect |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in c.pairs:
        w = p.power
        powers = (
            f"{number(w.difference)} ({w.effect_size:+.2f}) | {w.power:.0%} "
            f"| {w.seeds if w.seeds is not None else f'> {MAX_SEEDS}'} "
            f"| {w.power_for_smallest:.0%} (difference {number(w.smallest)})"
            if w is not None
            else "- | - | - | -"
        )
        out.append(
            f"| {p.a} vs {p.b} | {QUANTITY_NAMES[p.quantity]} | {interval(*p.p_improvement)} "
            f"| {p.p_value:.3g} | {powers} |"
        )
    return out


def _published_section(c: Comparison) -> list[str]:
    """Published figures for the algorithms in the report, beside what was measured here."""
    if not c.published:
        return []
    out = [
        "",
        "## Published reference figures",
        "",
        f"{PUBLISHED_CAVEAT} This report measured {c.env_id} ({budgets_text(c)}).",
        "",
        f"| algorithm | env (published) | steps | return ± std | source | measured here: IQM "
        f"of {c.score} |",
        "|---|---|---|---|---|---|",
    ]
    for fig in c.published:
        std = f" ± {fig['std']:,}" if fig.get("std") is not None else ""  # as published
        measured = "; ".join(
            f"{r.algo} {interval(*r.iqm)}" for r in c.algos if r.algorithm == fig["algo"]
        )
        out.append(
            f"| {fig['algo']} | {_version(fig.get('env_version'), c.env_id)} "
            f"| {number(fig.get('steps'))} "
            f"| {fig['return']:,}{std} (published) | {fig.get('source', '?')} | {measured} |"
        )
    return out


def _version(published: str | None, measured: str) -> str:
    """The published env version, said to be the measured one or another."""
    if published is None:
        return "?"
    return f"{published} ({'same version' if published == measured else 'other version'})"


def _title(c: Comparison) -> str:
    if c.group_by:
        algorithms = ", ".join(dict.fromkeys(r.algorithm for r in c.algos))
        return f"# {algorithms} on {c.env_id} by {', '.join(c.group_by)}"
    return f"# {' vs '.join(r.algo for r in c.algos)} on {c.env_id}"


def markdown(c: Comparison, source: str) -> str:
    level = f"{c.confidence:.0%}"
    out = [_title(c), "", verdict(c), ""]
    out += [
        f"Runs from {source}; budget {budgets_text(c)}; score `{c.score}`; threshold "
        f"{number(c.threshold)}. IQM = interquartile mean; CIs are {level} percentile bootstraps "
        "over seeds (stratified per env); P(A > B) is the probability that a random seed of A "
        "beats a random seed of B (Mann-Whitney U / nm), after Agarwal et al. 2021. A verdict "
        f"needs the CI of P(A > B) to exclude 0.5 and Mann-Whitney p < {1 - c.confidence:.2g}.",
        "",
        "## Per arm",
        "",
        f"| arm | seeds | {c.score} mean ± std | IQM [{level} CI] | AUC mean ± std "
        "| steps to threshold (median) | seeds reaching it | CPU-hours, seeds summed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in c.algos:
        d = r.as_dict()
        out.append(
            f"| {r.label} | {d['seeds']} | {number(d['score_mean'])} ± {number(d['score_std'])} "
            f"| {interval(*r.iqm)} | {number(d['auc_mean'])} ± {number(d['auc_std'])} "
            f"| {_steps(d['steps_to_threshold_median'], r.x_axis)} "
            f"| {d['threshold_reached']}/{d['seeds']} "
            f"| {formatting.cpu_hours(d['cpu_hours'], d['cpu_hours_runs'], d['seeds'])} |"
        )
    out += _published_section(c)
    out += _arms_section(c)
    out += _pairwise_section(c, level)
    methods = sorted({p.power.method for p in c.pairs if p.power is not None})
    if methods:
        out += [
            "",
            f"Power (at alpha {1 - c.confidence:.2g}, for the report's Mann-Whitney test) by "
            f"{' and '.join(methods)}: the closed form where both arms' returns look normal, "
            "else studies resampled from the runs themselves (walkers/analysis/power.py). "
            "`python -m walkers.plan` plans a study from these runs.",
        ]
    for r in c.algos:
        out += _normalized_lines(r, c.score) + _per_target_lines(r)
    if len(c.grids) > 1:
        out += [
            "",
            "Online and offline runs are compared on final return only: their AUCs are means "
            "over different x-axes (env steps vs gradient steps on a fixed dataset).",
        ]
    out += [
        "",
        "## Learning curves",
        "",
        "![learning curves](learning_curves.png)",
        "",
        "![scores](scores.png)",
    ]
    if c.group_by:
        out += ["", f"![score by {', '.join(c.group_by)}](group_by.png)"]
    out += [
        "",
        "## Runs",
        "",
        f"| arm | seed | run id | {c.score} | AUC | steps to threshold |",
        "|---|---|---|---|---|---|",
    ]
    for r in c.algos:
        for run in r.runs:
            s = run.summary
            out.append(
                f"| {r.algo} | {run.seed} | `{run.named}` | {number(s[c.score])} "
                f"| {number(s['final/auc'])} | {_steps(s['final/steps_to_threshold'], r.x_axis)} |"
            )
    if c.references:
        out += ["", "## Arms from references", ""]
        out += [
            "These arms were not run for this report: their seeds come from results bundles, "
            "checked like for like (env, evaluation protocol, budget, and the update's "
            "fingerprint under today's code).",
            "",
            "| bundle | arms | runs | from | commits | packages | devices "
            "| CPU-hours, runs summed |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for ref in c.references:
            hours = "" if ref["cpu_hours"] is None else f"{ref['cpu_hours']:.3g}"
            out.append(
                f"| `{ref['path']}` | {', '.join(ref['arms'])} | {ref['runs']} "
                f"| experiment {ref['experiment']!r}, {ref['selection']} "
                f"| {', '.join(c[:10] for c in ref['commits'])} | {'; '.join(ref['packages'])} "
                f"| {', '.join(ref['devices'])} | {hours} |"
            )
    if c.left_out:
        out += ["", "## Left out", ""] + [f"- {note}" for note in c.left_out]
    return "\n".join(out) + "\n"


def write_report(c: Comparison, out: Path, source: str) -> list[Path]:
    """``report.md``, ``summary.json``, ``learning_curves.png``, ``scores.png`` in ``out``, and
    ``group_by.png`` for a ``group_by`` study."""
    out.mkdir(parents=True, exist_ok=True)
    report = out / "report.md"
    report.write_text(markdown(c, source))
    summary = out / "summary.json"
    summary.write_text(json.dumps(c.as_dict(), indent=2))
    files = [
        report,
        summary,
        plot_learning_curves(c, out / "learning_curves.png"),
        plot_scores(c, out / "scores.png"),
    ]
    if c.group_by:
        files.append(plot_group_by(c, out / "group_by.png"))
    return files
