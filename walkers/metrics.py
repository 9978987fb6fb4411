"""The run-summary metrics: how a run's ``final/*`` are computed from its evaluations
(:func:`run_summary`), which of them an Optuna sweep may optimize, and which way is better.

A sweep's direction follows its ``optimized_metric`` through this one table
(:mod:`walkers.tuning.optuna_sweeper`), so no study can reward slowness by maximizing
``final/steps_to_threshold``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from walkers.errors import ConfigError

MAXIMIZE = "maximize"
MINIMIZE = "minimize"

METRIC_DIRECTIONS: dict[str, str] = {
    "final/return_mean": MAXIMIZE,  # the last evaluation's mean return
    "final/return_last10": MAXIMIZE,  # mean of the last 10 evaluations
    "final/auc": MAXIMIZE,  # mean eval return over the run: the rate of learning
    "final/normalized_score": MAXIMIZE,  # offline runs: 0 = a random policy, 100 = the expert
    "final/steps_to_threshold": MINIMIZE,  # first env step at env.threshold; inf: never reached
}


def normalized_score(score: float, random: float, reference: float) -> float:
    """rliable's and D4RL's normalized score: 0 is a random policy, 100 the reference score."""
    return 100.0 * (score - random) / (reference - random)


def allowed_metrics() -> str:
    """``final/auc (maximized), ...``: the table, for error messages."""
    return ", ".join(f"{metric} ({direction}d)" for metric, direction in METRIC_DIRECTIONS.items())


def metric_direction(metric: str) -> str:
    """``maximize`` or ``minimize``: which way ``metric`` is better."""
    try:
        return METRIC_DIRECTIONS[metric]
    except KeyError:
        raise ConfigError(
            f"optimized_metric={metric!r} is not allowed: must be one of {allowed_metrics()}"
        ) from None


def auc(eval_means: Sequence[float]) -> float:
    """Area under the learning curve, normalized: the mean eval return over the whole run.

    Evaluations are equally spaced in env steps, so this is the rate of learning: two agents
    with the same final return differ here when one got there sooner.
    """
    return float(np.mean(eval_means))


def steps_to_threshold(
    steps: Sequence[int], eval_means: Sequence[float], threshold: float
) -> float:
    """First env step whose eval mean return reaches ``threshold``; ``inf`` if none did."""
    for step, value in zip(steps, eval_means, strict=True):
        if value >= threshold:
            return float(step)
    return math.inf


def run_summary(steps: Sequence[int], eval_means: Sequence[float], threshold: float) -> dict:
    """The ``final/*`` metrics of a run from its evaluation history."""
    if len(eval_means) == 0:
        return {}
    return {
        "final/return_mean": float(eval_means[-1]),
        "final/return_last10": float(np.mean(eval_means[-10:])),
        "final/auc": auc(eval_means),
        "final/steps_to_threshold": steps_to_threshold(steps, eval_means, threshold),
    }
