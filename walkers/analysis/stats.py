"""The statistics of every report, defined once (Agarwal et al. 2021's, as rliable computes them),
with SciPy: the pairwise comparison, the suite report and an A/B study's rounds all use these.

Per run: :func:`auc`, :func:`steps_to_threshold`, :func:`run_summary` (the ``final/*`` metrics,
defined in :mod:`walkers.metrics`, where the trainer reads them too).

Across runs, each statistic of *tasks* (envs or datasets), each task an array of its seeds'
scores (a single task: the seeds of one env):

- the aggregates (:data:`AGGREGATES`): the mean and the median over tasks of each task's mean
  score (rliable's ``aggregate_median``, not the median of the pooled runs), the IQM (the mean of
  the middle 50% of the pooled (task, seed) scores, ``scipy.stats.trim_mean(x, 0.25)``) and the
  optimality gap (the pooled mean shortfall below 100: ``mean(max(100 - x, 0))``);
- P(A > B): the chance a random seed of A beats a random seed of B, ties counting half (the
  Mann-Whitney U / nm), averaged over the tasks both arms ran (:func:`average_improvement`);
- the performance profile, and sample efficiency (the IQM of normalized returns per step).

Every CI is one bootstrap (:func:`bootstrap_ci`, ``scipy.stats.bootstrap``, percentile): each
task's seeds resampled within the task (rliable's ``StratifiedBootstrap``), so no replicate
ever drops a task; with one task it is the plain bootstrap over seeds. A task of one seed is
held fixed (nothing to resample). Tests pin every point to rliable 1.2.0's own numbers.

A test per env and pair: :func:`mann_whitney_p`; over a family of them, :func:`holm`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy import stats as sps

from walkers.metrics import auc, run_summary, steps_to_threshold

__all__ = ["auc", "run_summary", "steps_to_threshold"]  # and the statistics across seeds below

#: Percentile bootstrap, as rliable: stable for the tiny samples (3-10 seeds) RL studies have.
BOOTSTRAP_METHOD = "percentile"

#: A statistic of tasks: ``f(*tasks, axis=-1)``, each task its seeds' scores along ``axis``,
#: vectorized over the leading axes (the bootstrap hands it a batch of resamples at once).
TaskStatistic = Callable[..., np.ndarray]


# --- the aggregates ---------------------------------------------------------------------------
def iqm(scores, axis: int = -1):
    """Interquartile mean: the mean of the middle 50% (robust to one lucky or broken seed)."""
    return sps.trim_mean(scores, 0.25, axis=axis)


def _task_means(tasks, axis: int) -> np.ndarray:
    return np.stack([np.mean(task, axis=axis) for task in tasks])


def mean_of_tasks(*tasks, axis: int = -1):
    """The mean over tasks of each task's mean score."""
    return np.mean(_task_means(tasks, axis), axis=0)


def median_of_tasks(*tasks, axis: int = -1):
    """The median over tasks of each task's mean score (rliable's ``aggregate_median``)."""
    return np.median(_task_means(tasks, axis), axis=0)


def pooled_iqm(*tasks, axis: int = -1):
    """The IQM of the pooled (task, seed) scores."""
    return iqm(np.concatenate(tasks, axis=axis), axis=axis)


def optimality_gap(*tasks, axis: int = -1, target: float = 100.0):
    """The pooled mean shortfall below ``target``: ``mean(max(target - x, 0))``."""
    return np.mean(np.maximum(target - np.concatenate(tasks, axis=axis), 0.0), axis=axis)


#: rliable's aggregates, by the name reports give them.
AGGREGATES: dict[str, TaskStatistic] = {
    "mean": mean_of_tasks,
    "median": median_of_tasks,
    "IQM": pooled_iqm,
    "optimality gap": optimality_gap,
}


# --- one bootstrap ----------------------------------------------------------------------------
def bootstrap_ci(
    samples: Sequence, statistic: TaskStatistic, confidence: float, n_resamples: int, seed: int
) -> tuple[float, float] | tuple[np.ndarray, np.ndarray]:
    """``(low, high)``: the percentile-bootstrap CI of ``statistic(*samples)``, every sample
    resampled independently along its first axis (a task's seeds: a stratified bootstrap). A
    sample of one seed is held as it is; with none to resample the CI is the point."""
    samples = [np.asarray(s, dtype=float) for s in samples]
    free = [i for i, s in enumerate(samples) if len(s) > 1]
    if not free:
        point = statistic(*[np.moveaxis(s, 0, -1) for s in samples])
        return _scalar(point), _scalar(point)

    def with_fixed(*resampled, axis=-1):
        # SciPy hands the resamples seeds last, a batch of resamples just before: (..., B, n)
        tasks = [np.moveaxis(s, 0, -1) for s in samples]
        if resampled[0].ndim > tasks[free[0]].ndim:  # held samples join every resample
            b = resampled[0].shape[-2]
            tasks = [
                np.broadcast_to(t[..., None, :], (*t.shape[:-1], b, t.shape[-1])) for t in tasks
            ]
        for i, draw in zip(free, resampled, strict=True):
            tasks[i] = draw
        return statistic(*tasks, axis=axis)

    result = sps.bootstrap(
        tuple(samples[i] for i in free),
        with_fixed,
        n_resamples=n_resamples,
        confidence_level=confidence,
        method=BOOTSTRAP_METHOD,
        vectorized=True,
        axis=0,
        rng=np.random.default_rng(seed),
    )
    return _scalar(result.confidence_interval.low), _scalar(result.confidence_interval.high)


def _scalar(x):
    return float(x) if np.ndim(x) == 0 else np.asarray(x)


def aggregate_cis(
    per_task: Mapping[str, Sequence[float]],
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> dict[str, tuple[float, float, float]]:
    """Each aggregate of an arm's scores per task (task -> its seeds' scores):
    ``name -> (point, low, high)``."""
    tasks = [np.asarray(x, dtype=float) for x in per_task.values()]
    return {
        name: (float(f(*tasks)), *bootstrap_ci(tasks, f, confidence, n_resamples, seed))
        for name, f in AGGREGATES.items()
    }


def iqm_ci(
    scores_per_task: Sequence[Sequence[float]],
    confidence: float = 0.95,
    n_resamples: int = 5000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """IQM of all runs' scores and its stratified-bootstrap CI: ``(iqm, low, high)``; no CI
    (NaN) where a task has a single seed."""
    tasks = [np.asarray(t, dtype=float) for t in scores_per_task]
    point = float(pooled_iqm(*tasks))
    if min(len(t) for t in tasks) < 2:
        return point, math.nan, math.nan
    return (point, *bootstrap_ci(tasks, pooled_iqm, confidence, n_resamples, seed))


# --- P(A > B) ---------------------------------------------------------------------------------
def improvement(a, b, axis: int = -1):
    """P(X > Y) for X ~ a, Y ~ b, ties counting one half (vectorized over leading axes)."""
    a = np.moveaxis(np.asarray(a), axis, -1)[..., :, None]
    b = np.moveaxis(np.asarray(b), axis, -1)[..., None, :]
    return ((a > b) + 0.5 * (a == b)).mean(axis=(-2, -1))


def probability_of_improvement(a: Sequence[float], b: Sequence[float]) -> float:
    """P(A > B): the chance a random seed of A beats a random seed of B (Mann-Whitney U / nm)."""
    return float(improvement(a, b))


def a_ranks_higher(a: Sequence[float], b: Sequence[float]) -> bool:
    """Whether A's seeds rank above B's (P(A > B) > 1/2): the side a rank test's rejection
    favours, which one outlier seed can flip in the means but not here."""
    return probability_of_improvement(a, b) > 0.5


def poi_ci(
    a: Sequence[float],
    b: Sequence[float],
    confidence: float = 0.95,
    n_resamples: int = 5000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """P(A > B) on one task and its bootstrap CI (both arms' seeds resampled): ``(p, low,
    high)``; no CI (NaN) with a single seed on either side."""
    point = probability_of_improvement(a, b)
    if min(len(a), len(b)) < 2:
        return point, math.nan, math.nan
    return (point, *bootstrap_ci((a, b), improvement, confidence, n_resamples, seed))


def average_improvement(
    a: Mapping[str, Sequence[float]],
    b: Mapping[str, Sequence[float]],
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """P(A > B) averaged over the tasks both arms ran (task -> seeds' scores), with a
    stratified bootstrap CI: ``(p, low, high)``."""
    tasks = [task for task in a if task in b]
    n = len(tasks)

    def averaged(*samples, axis=-1):
        return np.mean([improvement(samples[i], samples[n + i], axis) for i in range(n)], axis=0)

    samples = [np.asarray(a[t], dtype=float) for t in tasks]
    samples += [np.asarray(b[t], dtype=float) for t in tasks]
    point = float(averaged(*samples))
    return (point, *bootstrap_ci(samples, averaged, confidence, n_resamples, seed))


# --- profiles and curves ----------------------------------------------------------------------
def performance_profile(per_task: Mapping[str, np.ndarray], taus: np.ndarray) -> np.ndarray:
    """The fraction of runs whose normalized score is above each tau, each task's fraction
    weighed alike (rliable's run-score profile): a task with more seeds does not count more."""
    taus = np.asarray(taus)[:, None]
    return np.mean([(np.asarray(x)[None, :] > taus).mean(axis=1) for x in per_task.values()], 0)


def iqm_curve(
    curves: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]],
    grid: np.ndarray,
    confidence: float = 0.95,
    n_resamples: int = 500,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample efficiency: per step of ``grid``, the IQM over (task, seed) of the normalized eval
    returns (``curves``: task -> each seed's (steps, normalized returns)), with a stratified
    bootstrap band: ``(iqm, low, high)``."""
    tasks = [
        np.array([np.interp(grid, steps, values) for steps, values in runs])
        for runs in curves.values()
    ]  # each (seeds, grid)
    point = pooled_iqm(*[t.T for t in tasks])
    low, high = bootstrap_ci(tasks, pooled_iqm, confidence, n_resamples, seed)
    return point, low, high


def mean_band(
    curves: np.ndarray, confidence: float = 0.95, n_resamples: int = 2000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean curve over seeds (rows) and a bootstrap CI band per column: ``(mean, low, high)``.

    With a single seed the band is the curve itself (there is nothing to resample).
    """
    curves = np.asarray(curves, dtype=float)
    mean = curves.mean(axis=0)
    if curves.shape[0] < 2:
        return mean, mean.copy(), mean.copy()

    def seeds_mean(seeds, axis=-1):
        return np.mean(seeds, axis=axis)

    low, high = bootstrap_ci([curves], seeds_mean, confidence, n_resamples, seed)
    return mean, low, high


# --- tests ------------------------------------------------------------------------------------
def mann_whitney_p(a: Sequence[float], b: Sequence[float], alternative: str = "two-sided") -> float:
    """Mann-Whitney U test p-value: exact without ties (valid at the tiny levels a family of
    questions needs), else the normal approximation, never below the exact test's smallest p
    (seeds tied at a capped return, InvertedPendulum's 1000, made it 0.044 for 3 against 4
    seeds, where no ordering of 7 seeds gives less than 0.057)."""
    if min(len(a), len(b)) < 1:
        return math.nan
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    tied = len(np.unique(np.concatenate([a, b]))) < len(a) + len(b)
    method = "asymptotic" if tied else "exact"
    p = float(sps.mannwhitneyu(a, b, alternative=alternative, method=method).pvalue)
    if not tied:
        return p
    floor = (2 if alternative == "two-sided" else 1) / math.comb(len(a) + len(b), len(a))
    return max(p, min(1.0, floor))


def holm(p_values: Mapping[str, float]) -> dict[str, float]:
    """Holm's step-down adjusted p-values (family-wise error over all the given tests)."""
    order = sorted(p_values, key=p_values.get)
    m, running, adjusted = len(order), 0.0, {}
    for i, key in enumerate(order):
        running = max(running, min(1.0, (m - i) * p_values[key]))
        adjusted[key] = running
    return adjusted
