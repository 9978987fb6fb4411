"""Learning-curve summaries and statistics (Agarwal et al. 2021 definitions, with SciPy)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


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
