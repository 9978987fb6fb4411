"""The A/B study's stopping rule by simulation: family-wise error and seeds saved.

    python benchmarks/bench_sequential.py [--studies 1000]       (make bench-sequential)

For a one-pair study (TD3 vs REINFORCE on one env: seeds 5..15, 2 per round) and a suite study
(3 arms x 4 envs + the aggregate, 15 questions: seeds 8..20, 4 per round), under three shapes of
returns (normal; bimodal: 30% of seeds fail; heavy-tailed: Student t with 2 df), each studied
through the study's own round logic (walkers.ab.rounds):

- under "no difference": the family-wise error rate (any false "better" or false "equal");
- under a difference between two arms (1.5 spreads: a close race; 4 spreads: TD3 against
  REINFORCE), the other arms equal: the power (the right "better" answer),
  the mean seeds per arm the sequential study ran, and the seeds per arm of the fixed-n design
  (one look, the same test at the same level per question) whose simulated power is the same.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import stats as sps

from walkers.ab.simulation import SHAPES, draw, simulate, spec_for
from walkers.analysis.sequential import A_BETTER

SPREAD = 10.0
EFFECTS = (15.0, 40.0)
DESIGNS = {
    "1 pair, 1 env": dict(arms=2, envs=1, seeds=(5, 15, 2)),
    "3 arms x 4 envs": dict(arms=3, envs=4, seeds=(8, 20, 4)),
}


def fixed_n_power(n: int, effect: float, level: float, shape: str, studies: int, rng) -> float:
    a = effect + draw(shape, rng, (studies, n), SPREAD)
    b = draw(shape, rng, (studies, n), SPREAD)
    p = sps.mannwhitneyu(a, b, alternative="two-sided", axis=1).pvalue
    return float(np.mean((p <= level) & (np.median(a, axis=1) > np.median(b, axis=1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--studies", type=int, default=1000)
    args = parser.parse_args()
    print(
        "| design | returns | family-wise error (alpha 0.05) | difference (spreads) | power | "
        "mean seeds per arm and env, sequential | fixed n of the same power | seeds saved |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, shape_of in DESIGNS.items():
        studies = args.studies if shape_of["arms"] == 2 else max(50, args.studies // 10)
        spec = spec_for(alpha=0.05, delta=10.0, **shape_of)
        arms = [a.name for a in spec.arms]
        cells = len(arms) * len(spec.envs)
        for shape in SHAPES:
            rng = np.random.default_rng(0)
            null = {arm: 50.0 for arm in arms}
            fwer = np.mean([simulate(spec, null, shape, SPREAD, rng).wrong for _ in range(studies)])
            for effect in EFFECTS:
                means = null | {arms[0]: 50.0 + effect}
                runs = [simulate(spec, means, shape, SPREAD, rng) for _ in range(studies)]
                first = f"{arms[0]} vs {arms[1]} on env0"
                power = np.mean([o.decisions[first] == A_BETTER for o in runs])
                seeds = np.mean([o.seeds for o in runs]) / cells
                level = spec.design().alpha_per_question
                fixed = next(
                    (
                        n
                        for n in range(2, 200)
                        if fixed_n_power(n, effect, level, shape, 2000, rng) >= power
                    ),
                    None,
                )
                saved = f"{1 - seeds / fixed:.0%}" if fixed else "n/a"
                print(
                    f"| {label} | {shape} | {fwer:.3f} ({studies} studies) | {effect / SPREAD:g} "
                    f"| {power:.2f} | {seeds:.1f} | {fixed} | {saved} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
