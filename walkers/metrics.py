"""The run-summary metrics an Optuna sweep may optimize, and which way is better for each.

A sweep's direction follows its ``optimized_metric`` through this one table
(:mod:`walkers.tuning.sweeper`), so no study can reward slowness by maximizing
``final/steps_to_threshold``.
"""

from __future__ import annotations

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
