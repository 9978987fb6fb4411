"""Studies simulated through the study's own decision code (:func:`walkers.ab.rounds.standing`),
round by round, as the sweeper runs them: the family-wise error rate and the seeds a study uses.

Returns are drawn per arm, env and seed from one of three shapes, all scaled to the env's
normalized units: ``normal``; ``bimodal`` (a seed learns or it does not, as RL seeds do: 70% at
the arm's level, 30% far below); ``heavy`` (Student t with 2 degrees of freedom: rare seeds far
off). Used by ``tests/analysis/test_sequential.py`` and ``benchmarks/bench_sequential.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from walkers.ab.rounds import standing
from walkers.ab.spec import Arm, EnvScores, StudySpec
from walkers.analysis.sequential import A_BETTER, B_BETTER, EQUAL

SHAPES = ("normal", "bimodal", "heavy")


def draw(shape: str, rng: np.random.Generator, size: int, spread: float) -> np.ndarray:
    """Zero-median noise of the given shape, ``spread`` its scale (normalized points)."""
    if shape == "normal":
        return rng.normal(0, spread, size)
    if shape == "bimodal":
        fails = rng.random(size) < 0.3
        return rng.normal(0, spread / 2, size) - fails * 4 * spread
    if shape == "heavy":
        return rng.standard_t(2, size) * spread
    raise ValueError(f"shape={shape!r}: one of {SHAPES}")


def spec_for(arms: int, envs: int, seeds: tuple[int, int, int], alpha: float, delta: float):
    """A study of ``arms`` x ``envs`` (normalized scores: random 0, reference 100)."""
    env_names = tuple(f"env{i}" for i in range(envs))
    return StudySpec(
        name="simulated",
        arms=tuple(Arm(f"arm{i}", ()) for i in range(arms)),
        envs=env_names,
        seeds_min=seeds[0],
        seeds_max=seeds[1],
        per_round=seeds[2],
        score="final/return_mean",
        alpha=alpha,
        smallest_difference=delta,
        scores={env: EnvScores(0.0, 100.0) for env in env_names},
    )


@dataclass
class Outcome:
    wrong: bool  # any question answered wrongly (a false "better", or "equal" when it is not)
    seeds: int  # seeds run in all (every arm and env)
    decisions: dict  # question name -> decision


def simulate(
    spec: StudySpec, means: dict[str, float], shape: str, spread: float, rng: np.random.Generator
) -> Outcome:
    """One study, round by round. ``means``: each arm's true level (normalized points, the same
    on every env). A "better" is wrong if the arms' means are equal or the other way round; an
    "equal" is wrong if they differ by ``smallest_difference`` or more."""
    pool = {
        (arm.name, env): means[arm.name] + draw(shape, rng, spec.seeds_max, spread)
        for arm in spec.arms
        for env in spec.envs
    }
    scores: dict = {key: {} for key in pool}
    while True:
        now = standing(spec, scores)
        jobs = now.missing(scores)
        if not jobs:
            break
        for arm, env, seed in jobs:
            scores[(arm, env)][seed] = float(pool[(arm, env)][seed])
    wrong = False
    for q in now.questions:
        diff = means[q.a] - means[q.b]
        d = q.answer.decision
        if (d == A_BETTER and diff <= 0) or (d == B_BETTER and diff >= 0):
            wrong = True
        if d == EQUAL and abs(diff) >= spec.smallest_difference:
            wrong = True
    return Outcome(
        wrong,
        sum(len(v) for v in scores.values()),
        {q.name: q.answer.decision for q in now.questions},
    )
