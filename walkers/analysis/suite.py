"""Aggregates over a suite of envs, as rliable defines them (Agarwal et al. 2021), with SciPy.

Every score is first normalized per env: 100 x (score - random) / (reference - random), both
references from ``conf/env/<env>.yaml`` (``scores``). An arm's runs over the suite are then the
(env, seed) pairs, and:

- the aggregates of rliable's ``metrics`` module, each with a *stratified* bootstrap CI (seeds
  resampled within each env, never across envs): the mean (over envs of each env's mean score),
  the median (over envs of each env's mean score: rliable's ``aggregate_median``, not the
  median of the pooled runs), the IQM (the mean of the middle 50% of the pooled (env, seed)
  scores, ``scipy.stats.trim_mean(x, 0.25)``) and the optimality gap (the pooled mean shortfall
  below 100: ``mean(max(100 - x, 0))``); ``tests/analysis/test_suite.py`` pins each to values
  rliable 1.2.0 itself computed on a fixture;
- P(A > B) averaged over envs (per env the Mann-Whitney U / nm of the two arms' seeds), with
  the same stratified bootstrap;
- the performance profile: the fraction of an arm's runs whose normalized score exceeds tau;
- sample efficiency: the IQM over (env, seed) of normalized eval returns at each step.

Per env and pair, the report's own test (two-sided Mann-Whitney) gives a p-value; across all
pairs and envs they are corrected by Holm's step-down method (family-wise error at alpha).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy import stats as sps

#: arm -> env -> normalized scores of its seeds
Suite = Mapping[str, Mapping[str, np.ndarray]]


def iqm(x: np.ndarray) -> float:
    return float(sps.trim_mean(x, 0.25))


def optimality_gap(x: np.ndarray, target: float = 100.0) -> float:
    return float(np.mean(np.maximum(target - x, 0.0)))


def _env_means(per_env: Mapping[str, np.ndarray]) -> np.ndarray:
    return np.array([np.mean(x) for x in per_env.values()])


def _pooled(per_env: Mapping[str, np.ndarray]) -> np.ndarray:
    return np.concatenate(list(per_env.values()))


#: rliable's aggregates, each of an arm's normalized scores per env (env -> its seeds' scores).
AGGREGATES: dict[str, Callable[[Mapping[str, np.ndarray]], float]] = {
    "mean": lambda per_env: float(np.mean(_env_means(per_env))),
    "median": lambda per_env: float(np.median(_env_means(per_env))),
    "IQM": lambda per_env: iqm(_pooled(per_env)),
    "optimality gap": lambda per_env: optimality_gap(_pooled(per_env)),
}


def _stratified(per_env: Mapping[str, np.ndarray], rng: np.random.Generator) -> dict:
    """One stratified resample: each env's seeds drawn with replacement, within the env."""
    return {env: rng.choice(x, size=len(x), replace=True) for env, x in per_env.items()}


def _interval(values: Sequence[float], confidence: float) -> tuple[float, float]:
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def aggregate_cis(
    per_env: Mapping[str, np.ndarray],
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> dict[str, tuple[float, float, float]]:
    """Each aggregate of an arm's scores per env: ``(point, low, high)``."""
    rng = np.random.default_rng(seed)
    draws = [_stratified(per_env, rng) for _ in range(n_resamples)]
    return {
        name: (f(per_env), *_interval([f(d) for d in draws], confidence))
        for name, f in AGGREGATES.items()
    }


def improvement(a: np.ndarray, b: np.ndarray) -> float:
    """P(A > B) on one env: a random seed of A beats a random seed of B (ties count half)."""
    return float(((a[:, None] > b[None, :]) + 0.5 * (a[:, None] == b[None, :])).mean())


def average_improvement(
    a: Mapping[str, np.ndarray],
    b: Mapping[str, np.ndarray],
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """P(A > B) averaged over the envs both arms ran, with a stratified bootstrap CI."""
    envs = [env for env in a if env in b]
    point = float(np.mean([improvement(a[env], b[env]) for env in envs]))
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(n_resamples):
        ra, rb = (
            _stratified({e: a[e] for e in envs}, rng),
            _stratified({e: b[e] for e in envs}, rng),
        )
        draws.append(np.mean([improvement(ra[e], rb[e]) for e in envs]))
    return (point, *_interval(draws, confidence))


def performance_profile(per_task: Mapping[str, np.ndarray], taus: np.ndarray) -> np.ndarray:
    """The fraction of runs whose normalized score is above each tau, each task's fraction
    weighed alike (rliable's run-score profile): an env with more seeds does not count more."""
    taus = np.asarray(taus)[:, None]
    return np.mean([(np.asarray(x)[None, :] > taus).mean(axis=1) for x in per_task.values()], 0)


def holm(p_values: Mapping[str, float]) -> dict[str, float]:
    """Holm's step-down adjusted p-values (family-wise error over all the given tests)."""
    order = sorted(p_values, key=p_values.get)
    m, running, adjusted = len(order), 0.0, {}
    for i, key in enumerate(order):
        running = max(running, min(1.0, (m - i) * p_values[key]))
        adjusted[key] = running
    return adjusted


def iqm_curve(
    curves: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]],
    grid: np.ndarray,
    confidence: float = 0.95,
    n_resamples: int = 500,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample efficiency: per step of ``grid``, the IQM over (env, seed) of the normalized eval
    returns (``curves``: env -> each seed's (steps, normalized returns)), with a stratified
    bootstrap band: ``(iqm, low, high)``."""
    per_env = {
        env: np.array([np.interp(grid, steps, values) for steps, values in runs])
        for env, runs in curves.items()
    }
    pooled = np.concatenate(list(per_env.values()))
    point = sps.trim_mean(pooled, 0.25, axis=0)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(n_resamples):
        rows = [x[rng.integers(0, len(x), len(x))] for x in per_env.values()]
        draws.append(sps.trim_mean(np.concatenate(rows), 0.25, axis=0))
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(np.array(draws), [tail, 100 - tail], axis=0)
    return point, low, high
