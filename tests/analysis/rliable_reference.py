"""What rliable 1.2.0 itself computes on :data:`SCORES`, as JSON: ``python -m
tests.analysis.rliable_reference [reps]`` in an environment that has rliable (it does not install
beside this project's pandas 3: ``tests/analysis/test_rliable.py`` makes one apart, with
``rliable==1.2.0 'pandas<3'``). This file imports only numpy and rliable, so that it runs there.

The table: three tasks (envs), arm A with 5 seeds, arm B with 3, normalized scores."""

from __future__ import annotations

import json

import numpy as np

#: arm -> (runs x tasks) normalized scores; three tasks, unequal seeds per arm
SCORES = {
    "A": [[12.0, 85.0, 140.0], [-4.0, 91.0, 60.0], [30.0, 77.0, 105.0],
          [8.0, 99.0, 131.0], [21.0, 64.0, 88.0]],
    "B": [[2.0, 40.0, 95.0], [10.0, 55.0, 72.0], [-8.0, 61.0, 110.0]],
}  # fmt: skip
#: rliable's stratified bootstrap draws for every CI (its own default is 50,000)
REPS = 20_000


def main(reps: int = REPS) -> None:
    from rliable import library as rly
    from rliable import metrics

    scores = {arm: np.array(rows) for arm, rows in SCORES.items()}
    aggregates = {
        "mean": metrics.aggregate_mean,
        "median": metrics.aggregate_median,
        "IQM": metrics.aggregate_iqm,
        # our normalized scores are percent: the gap below 100, rliable's gamma
        "optimality gap": lambda x: metrics.aggregate_optimality_gap(x, gamma=100),
    }

    def all_aggregates(x):
        return np.array([f(x) for f in aggregates.values()])

    points, cis = rly.get_interval_estimates(scores, all_aggregates, reps=reps)
    out = {
        arm: {
            name: [float(points[arm][i]), float(cis[arm][0, i]), float(cis[arm][1, i])]
            for i, name in enumerate(aggregates)
        }
        for arm in scores
    }
    poi_points, poi_cis = rly.get_interval_estimates(
        {"A,B": (scores["A"], scores["B"])}, metrics.probability_of_improvement, reps=reps
    )
    low, high = np.ravel(poi_cis["A,B"])
    out["P(A > B)"] = [float(np.ravel(poi_points["A,B"])[0]), float(low), float(high)]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    import sys

    main(int(sys.argv[1]) if len(sys.argv) > 1 else REPS)
