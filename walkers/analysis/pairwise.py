"""The statistics of a comparison: per arm, its seeds' scores, their IQM and CI, per target
return (a DT's); per pair of arms, P(A > B) with its CI, the Mann-Whitney p and the power
(:func:`compare_groups`). Every statistic is :mod:`walkers.analysis.stats`'; the runs come from
``python -m walkers.compare`` (:mod:`walkers.analysis.comparison`)."""

from __future__ import annotations

from itertools import combinations

import numpy as np

from walkers.analysis import stats
from walkers.analysis.arms import Arm
from walkers.analysis.comparison_data import AlgoResult, Comparison, PairResult, SeedRun
from walkers.analysis.power import pair_power


def compare_groups(
    grouped: dict[str, list[SeedRun]],
    order: list[str],
    *,
    env_id: str,
    threshold: float,
    budgets: dict[str, int | dict[str, int]],
    score: str,
    confidence: float = 0.95,
    n_resamples: int = 5000,
    seed: int = 0,
    arms: dict[str, Arm] | None = None,
    smallest_effect: float = 0.1,
    smallest_effect_abs: float | None = None,
    pairs: list[tuple[str, str]] | None = None,
) -> Comparison:
    """Per-arm summaries and every pairwise comparison, in ``order`` (arm names, the keys of
    ``grouped``; ``arms`` describes them). Each pair's power is judged against the smallest
    difference worth detecting: ``smallest_effect_abs`` in the quantity's units, else
    ``smallest_effect`` times the larger of the two arms' absolute means. ``pairs``: the pairs
    of arm names to compare; None: every pair."""
    boot = {"confidence": confidence, "n_resamples": n_resamples, "seed": seed}
    results = []
    for name in order:
        runs = sorted(grouped[name], key=lambda r: r.seed)
        scores = np.array([r.summary[score] for r in runs])
        results.append(
            AlgoResult(
                algo=name,
                runs=runs,
                scores=scores,
                iqm=stats.iqm_ci([scores], **boot),
                auc=np.array([r.summary["final/auc"] for r in runs]),
                steps_to_threshold=np.array([r.summary["final/steps_to_threshold"] for r in runs]),
                arm=(arms or {}).get(name),
                per_target=_per_target(runs, boot),
            )
        )
    by_name = {r.algo: r for r in results}
    chosen = (
        combinations(results, 2) if pairs is None else [(by_name[a], by_name[b]) for a, b in pairs]
    )
    pairs = []
    for a, b in chosen:
        quantities = [("score", a.scores, b.scores)]
        if _same_evaluations(a, b):  # a rate of learning compares alike
            quantities.append(("auc", a.auc, b.auc))
        for quantity, xa, xb in quantities:
            smallest = smallest_effect_abs or smallest_effect * max(
                abs(np.mean(xa)), abs(np.mean(xb))
            )
            pairs.append(
                PairResult(
                    a.algo,
                    b.algo,
                    quantity,
                    stats.poi_ci(xa, xb, **boot),
                    stats.mann_whitney_p(xa, xb),
                    pair_power(xa, xb, 1 - confidence, smallest),
                )
            )
    grids = {}
    for res in results:
        steps = np.concatenate([r.steps for r in res.runs])
        grids[res.x_axis] = np.union1d(grids.get(res.x_axis, steps), steps)
    return Comparison(
        env_id=env_id,
        threshold=threshold,
        budgets=budgets,
        score=score,
        confidence=confidence,
        algos=results,
        pairs=pairs,
        grids=grids,
    )


def _per_target(runs: list, boot: dict) -> dict[str, tuple[float, float, float]]:
    """The IQM of the final returns and its CI at each target return that every seed of an arm
    was evaluated at (a DT's), highest target first; empty for other arms."""
    targets = set.intersection(*(set(r.final_per_target) for r in runs)) if runs else set()
    return {
        target: stats.iqm_ci([[r.final_per_target[target] for r in runs]], **boot)
        for target in sorted(targets, key=float, reverse=True)
    }


def _same_evaluations(a: AlgoResult, b: AlgoResult) -> bool:
    """Whether two arms' learning curves were measured alike: the same axis and budget, and the
    same evaluation steps. The AUC is the mean of the evaluations, so a coarser grid wins on a
    rising curve (a linear one over 100k steps: 50.5 every 1k, 75 every 50k)."""
    grids = {tuple(r.steps) for r in (*a.runs, *b.runs)}
    return (a.x_axis, a.budget) == (b.x_axis, b.budget) and len(grids) == 1
