"""``walkers.compare envs=[...]``: each env's own report, then the suite's (``<out>/../suite/``):
normalized scores, aggregates with stratified-bootstrap CIs, P(A > B) over envs, per-env tests
corrected by Holm's method, a performance profile and sample-efficiency curves
(:mod:`walkers.analysis.suite` has the definitions)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from walkers import CONF_DIR  # noqa: E402
from walkers.analysis import stats, suite  # noqa: E402
from walkers.analysis.comparison import compare  # noqa: E402
from walkers.errors import ConfigError  # noqa: E402

CORRECTION = "Holm's step-down method over every pair on every env"


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


def compare_suite(cfg: DictConfig) -> tuple[str, Path]:
    """Each env's comparison and report, then the suite's report; returns its verdict and dir."""
    if len(cfg.envs) < 2:
        raise ConfigError(f"envs={list(cfg.envs)} is not allowed: two or more conf/env names")
    envs = {name: env_config(name) for name in cfg.envs}
    comparisons = {}
    for name, env in envs.items():
        one = cfg.copy()
        one.env = env
        one.out = str(Path(cfg.out).parent / env.id)
        comparisons[name] = compare(one)[0]
    out = Path(cfg.out).parent / "suite"
    return write_suite(comparisons, envs, cfg, out), out


def _normalized(comparisons, envs) -> tuple[dict, dict]:
    """arm -> env -> normalized seed scores, and arm -> env -> normalized eval curves."""
    scores, curves = {}, {}
    arms = [r.algo for r in next(iter(comparisons.values())).algos]
    for name, comparison in comparisons.items():
        random, reference = envs[name].scores.random, envs[name].scores.reference
        norm = lambda x, lo=random, hi=reference: 100 * (np.asarray(x) - lo) / (hi - lo)  # noqa
        by_arm = {r.algo: r for r in comparison.algos}
        arms = [a for a in arms if a in by_arm]
        for arm in arms:
            scores.setdefault(arm, {})[name] = norm(by_arm[arm].scores)
            curves.setdefault(arm, {})[name] = [
                (r.steps, norm(r.returns)) for r in by_arm[arm].runs
            ]
    keep = [a for a in arms if all(name in scores.get(a, {}) for name in comparisons)]
    return {a: scores[a] for a in keep}, {a: curves[a] for a in keep}


def write_suite(comparisons, envs, cfg: DictConfig, out: Path) -> str:
    out.mkdir(parents=True, exist_ok=True)
    boot = {
        "confidence": cfg.confidence,
        "n_resamples": min(cfg.n_resamples, 2000),
        "seed": cfg.seed,
    }
    scores, curves = _normalized(comparisons, envs)
    if len(scores) < 1:
        raise ConfigError(f"no arm ran on every env of {list(envs)}: nothing to aggregate")
    aggregates = {arm: suite.aggregate_cis(per_env, **boot) for arm, per_env in scores.items()}
    pairs = list(itertools.combinations(scores, 2))
    raw_p = {
        f"{a} vs {b} on {env}": stats.mann_whitney_p(scores[a][env], scores[b][env])
        for a, b in pairs
        for env in envs
    }
    adjusted = suite.holm(raw_p)
    alpha = 1 - cfg.confidence
    improvement = {
        f"{a} vs {b}": suite.average_improvement(scores[a], scores[b], **boot) for a, b in pairs
    }

    lines = [
        f"# Suite: {', '.join(envs)}",
        "",
        "Normalized score = 100 x (score - random) / (reference - random), per env "
        f"(`conf/env/*.yaml` scores); score: `{cfg.score}`. Aggregates over (env, seed) follow "
        "rliable (Agarwal et al. 2021); CIs are stratified bootstraps (seeds resampled within "
        f"each env), {cfg.confidence:.0%}.",
        "",
        "| env | random | reference |",
        "|---|---|---|",
        *[f"| {name} | {e.scores.random:g} | {e.scores.reference:g} |" for name, e in envs.items()],
        "",
        "## Aggregates (normalized)",
        "",
        "| arm | " + " | ".join(suite.AGGREGATES) + " | runs |",
        "|---|" + "---|" * (len(suite.AGGREGATES) + 1),
    ]
    for arm, agg in aggregates.items():
        cells = [f"{p:.1f} [{lo:.1f}, {hi:.1f}]" for p, lo, hi in agg.values()]
        runs = sum(len(x) for x in scores[arm].values())
        lines.append(f"| {arm} | " + " | ".join(cells) + f" | {runs} |")
    lines += ["", "## Per env (normalized IQM)", "", "| arm | " + " | ".join(envs) + " |",
              "|---|" + "---|" * len(envs)]  # fmt: skip
    for arm in scores:
        lines.append(
            f"| {arm} | " + " | ".join(f"{suite.iqm(scores[arm][e]):.1f}" for e in envs) + " |"
        )
    lines += ["", "## Pairs", "", f"P(A > B) averaged over envs; per-env Mann-Whitney p, "
              f"corrected for {len(raw_p)} tests by {CORRECTION} (a difference needs adjusted p "
              f"< {alpha:.2g}).", "",
              "| pair | P(A > B) over envs | env | p | Holm-adjusted p | verdict |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for a, b in pairs:
        p, lo, hi = improvement[f"{a} vs {b}"]
        for env in envs:
            key = f"{a} vs {b} on {env}"
            diff = np.mean(scores[a][env]) - np.mean(scores[b][env])
            verdict = (
                f"{a if diff > 0 else b} better"
                if adjusted[key] < alpha
                else "no reliable difference"
            )
            lines.append(f"| {a} vs {b} | {p:.2f} [{lo:.2f}, {hi:.2f}] | {env} | {raw_p[key]:.4f} "
                         f"| {adjusted[key]:.4f} | {verdict} |")  # fmt: skip
    lines += ["", "![performance profile](performance_profile.png)",
              "![sample efficiency](sample_efficiency.png)", ""]  # fmt: skip
    (out / "report.md").write_text("\n".join(lines))
    _plots(scores, curves, out)
    summary = {
        "envs": {
            n: {"random": e.scores.random, "reference": e.scores.reference} for n, e in envs.items()
        },
        "aggregates": aggregates,
        "probability_of_improvement": improvement,
        "p_values": raw_p,
        "holm_adjusted": adjusted,
        "correction": CORRECTION,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    best = max(aggregates, key=lambda arm: aggregates[arm]["IQM"][0])
    top = aggregates[best]["IQM"][0]
    return f"suite of {len(envs)} envs: the highest normalized IQM is {best}'s ({top:.1f})"


def _plots(scores, curves, out: Path) -> None:
    taus = np.linspace(-10, 150, 161)
    fig, ax = plt.subplots(figsize=(6, 4))
    for arm, per_env in scores.items():
        ax.plot(
            taus, suite.performance_profile(np.concatenate(list(per_env.values())), taus), label=arm
        )
    ax.set(
        xlabel="normalized score tau", ylabel="fraction of runs > tau", title="Performance profile"
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "performance_profile.png", dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    for arm, per_env in curves.items():
        last = min(steps[-1] for runs in per_env.values() for steps, _ in runs)
        grid = np.linspace(0, last, 50)
        point, low, high = suite.iqm_curve(per_env, grid)
        ax.plot(grid, point, label=arm)
        ax.fill_between(grid, low, high, alpha=0.2)
    ax.set(xlabel="env steps", ylabel="IQM normalized eval return", title="Sample efficiency")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "sample_efficiency.png", dpi=100)
    plt.close(fig)
