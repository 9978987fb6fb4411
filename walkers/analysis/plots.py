"""The report's plots: learning curves with CI bands (one panel per x-axis, or per series of a
study), per-seed scores with the IQM, and a study's score against its ``group_by`` values."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402

from walkers.analysis import arms, stats  # noqa: E402
from walkers.analysis.comparison_data import AXIS_NAMES, AlgoResult, Comparison  # noqa: E402
from walkers.tracking.names import ENV_STEPS  # noqa: E402


def curves_on_grid(result: AlgoResult, grid: np.ndarray) -> np.ndarray:
    """Seeds x grid matrix of eval returns (runs evaluated at other steps are interpolated)."""
    return np.stack([np.interp(grid, r.steps, r.returns) for r in result.runs])


def _curve_panels(c: Comparison) -> list[tuple[str, str, list[AlgoResult]]]:
    """``(x-axis, title, arms)`` per panel: one per x-axis; in a study of ``group_by`` keys over
    several series (e.g. ``group_by=impl`` over algorithms), one per series and x-axis, so each
    panel shows the arms that its verdicts compare."""
    with_arms = all(r.arm is not None for r in c.algos)
    labels = arms.series([r.arm for r in c.algos]) if c.group_by and with_arms else {}
    panels: dict[tuple[str, str], list[AlgoResult]] = {}
    for result in c.algos:
        panels.setdefault((result.x_axis, labels.get(result.algo, "")), []).append(result)
    # a panel is named by its algorithm where that tells the panels apart, else by its series
    algorithms = {key: {r.algorithm for r in results} for key, results in panels.items()}
    by_algorithm = all(len(a) == 1 for a in algorithms.values()) and len(
        {next(iter(a)) for a in algorithms.values()}
    ) == len(panels)
    out = []
    for (axis, label_), results in panels.items():
        title = c.env_id if axis == ENV_STEPS else f"{c.env_id}, offline"
        name = results[0].algorithm if by_algorithm and label_ else textwrap.shorten(label_, 70)
        out.append((axis, f"{title}: {name}" if name else title, results))
    return out


def plot_learning_curves(c: Comparison, path: Path) -> Path:
    """One panel per x-axis (env steps; gradient steps for offline runs), or per series of a
    study (:func:`_curve_panels`), on a shared y-axis; the published reference figures of the
    panel's algorithms as dotted lines."""
    panels = _curve_panels(c)
    columns = min(len(panels), 4)
    rows = -(-len(panels) // columns)
    fig, axes = plt.subplots(
        rows, columns, figsize=(7 * columns, 4.5 * rows), sharey=True, squeeze=False
    )
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    color_of = {r.algo: colors[i % len(colors)] for i, r in enumerate(c.algos)}
    for ax, (axis, title, results) in zip(axes.flat, panels, strict=False):
        grid = c.grids[axis]
        for result in results:
            mean, low, high = stats.mean_band(curves_on_grid(result, grid), c.confidence)
            color = color_of[result.algo]
            ax.plot(grid, mean, color=color, label=f"{result.label} ({len(result.runs)} seeds)")
            ax.fill_between(grid, low, high, color=color, alpha=0.2, linewidth=0)
        algorithms = {r.algorithm for r in results}
        for fig_ in (f for f in c.published if f.get("algo") in algorithms):
            ax.axhline(
                fig_["return"],
                color="black",
                linestyle=":",
                linewidth=1,
                label=f"published {fig_['algo']} {fig_['return']:,} ({fig_.get('env_version')})",
            )
        ax.axhline(c.threshold, color="grey", linestyle="--", linewidth=1, label="threshold")
        ax.set_xlabel(AXIS_NAMES[axis])
        ax.set_title(title)
        ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_visible(False)
    for row in axes:
        row[0].set_ylabel(f"eval return (mean, {c.confidence:.0%} bootstrap CI)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_scores(c: Comparison, path: Path) -> Path:
    """Every seed's score as a dot, the IQM with its CI as a bar: nothing hidden in a mean."""
    fig, ax = plt.subplots(figsize=(1.6 * len(c.algos) + 2.5, 4))
    for i, result in enumerate(c.algos):
        ax.scatter([i] * len(result.scores), result.scores, alpha=0.6, zorder=3)
        point, low, high = result.iqm
        if not math.isnan(low):
            ax.errorbar(
                i + 0.15,
                point,
                yerr=[[point - low], [high - point]],
                fmt="none",
                ecolor="black",
                capsize=5,
            )
        ax.plot(i + 0.15, point, "k_", markersize=14)
    labels = [r.label for r in c.algos]
    long = max(map(len, labels)) > 16
    ax.set_xticks(
        range(len(c.algos)),
        labels,
        fontsize=8,
        rotation=20 if long else 0,
        ha="right" if long else "center",
    )
    ax.set_ylabel(f"{c.score} (dots: seeds; bar: IQM, {c.confidence:.0%} CI)")
    ax.set_title(c.env_id)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _group_positions(c: Comparison) -> tuple[list[str], dict[str, int]]:
    """The group_by values in report order (tick labels) and each arm's position among them."""
    labels: list[str] = []
    position = {}
    for r in c.algos:
        tick = " / ".join(r.arm.group_values.values())
        if tick not in labels:
            labels.append(tick)
        position[r.algo] = labels.index(tick)
    return labels, position


def plot_group_by(c: Comparison, path: Path) -> Path:
    """Score against the ``group_by`` values, in the report's (natural) order, evenly spaced:
    every seed a dot, the IQM with its CI a point and bar, one line per remaining configuration
    (one line unless the groups hold several)."""
    ticks, position = _group_positions(c)
    lines = arms.series([r.arm for r in c.algos])
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, ax = plt.subplots(figsize=(1.4 * len(ticks) + 3.5, 4.5))
    names = list(dict.fromkeys(lines.values()))
    for i, line in enumerate(names):
        members = [r for r in c.algos if lines[r.algo] == line]
        color, shift = colors[i % len(colors)], 0.08 * (i - (len(names) - 1) / 2)
        xs = [position[r.algo] + shift for r in members]
        for x, r in zip(xs, members, strict=True):
            dots = [x - 0.06] * len(r.scores)
            ax.scatter(dots, r.scores, color=color, alpha=0.35, s=14, zorder=2)
            point, low, high = r.iqm
            if not math.isnan(low):
                ax.errorbar(x, point, yerr=[[point - low], [high - point]], color=color, capsize=5)
        ax.plot(xs, [r.iqm[0] for r in members], "o-", color=color, label=line or None, zorder=3)
    ax.set_xticks(range(len(ticks)), ticks, fontsize=8)
    ax.set_xlim(-0.5, len(ticks) - 0.5)
    ax.set_xlabel(f"{' / '.join(c.group_by)} (sorted: numbers by value, lists by their sum)")
    ax.set_ylabel(f"{c.score}: IQM, {c.confidence:.0%} CI (dots: seeds)")
    ax.set_title(f"{c.env_id}: {c.score} by {', '.join(c.group_by)}")
    if any(names):
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def suite_plots(scores, curves, out: Path, axis: str, confidence: float) -> None:
    """A suite's performance profile and sample-efficiency curves (IQM with its band)."""
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
