"""PPO's time to walk: the wall time from a run's start to its first evaluation at or above a
return (3,000 on Walker2d-v5), through the platform itself, one configuration beside another.

    make bench-time-to-walk        # or: .venv/bin/python benchmarks/bench_time_to_walk.py \\
                                   #        --envs 1,8 --seeds 0,1,2 --budget 500000

Each (seed, configuration) is a real ``python -m walkers.train algo=ppo env=walker2d`` run with
``algo.num_envs`` envs (1: the reference's single env), one after another (the machine's cores
are the runs' own: do not run anything beside it), seeds taking turns between the
configurations so that machine noise hits all alike. A run is stopped (SIGINT: it ends KILLED,
checkpointed) once an evaluation reaches the return, or runs out its ``--budget`` of env steps.
The runs go to ``--store`` (an MLflow sqlite file, default ``.walkers/measure/time_to_walk.db``),
experiment ``time_to_walk``, so the measurement outlives the table:
``python -m walkers.export tracking.uri=sqlite:///... tracking.experiment=time_to_walk``.

The table: per configuration, each seed's minutes and env steps to the first evaluation at the
return (``-`` where the budget ran out first), the median over the seeds (a seed that never got
there counts as slower than any that did) and its ratio to the first configuration's. A
benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import math
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

from mlflow.tracking import MlflowClient

PROJECT = Path(__file__).resolve().parents[1]
EXPERIMENT = "time_to_walk"


def first_at(client: MlflowClient, run, threshold: float) -> tuple[float, int] | None:
    """(seconds from the run's start, env step) of its first evaluation >= ``threshold``."""
    history = client.get_metric_history(run.info.run_id, "eval/return_mean")
    reached = sorted((m for m in history if m.value >= threshold), key=lambda m: m.step)
    if not reached:
        return None
    return (reached[0].timestamp - run.info.start_time) / 1000, reached[0].step


def train_until(args, num_envs: int, seed: int, uri: str) -> tuple[float, int] | None:
    """One run; stopped once it walks. Returns what :func:`first_at` says."""
    key = f"time_to_walk/ppo/{num_envs}envs/{seed}"
    command = [
        sys.executable, "-m", "walkers.train", "algo=ppo", "env=walker2d", f"seed={seed}",
        f"algo.num_envs={num_envs}", f"total_steps={args.budget}", "torch_threads=1",
        "progress=false", f"tracking.uri={uri}", f"tracking.experiment={EXPERIMENT}",
        f"job_key={key}", *args.overrides,
    ]  # fmt: skip
    client = MlflowClient(uri)
    process = subprocess.Popen(command, cwd=PROJECT, stdout=subprocess.DEVNULL)
    try:
        while process.poll() is None:
            time.sleep(5)
            experiment = client.get_experiment_by_name(EXPERIMENT)
            if experiment is None:
                continue
            runs = client.search_runs(
                [experiment.experiment_id], f"tags.`walkers.job_key` = '{key}'", max_results=1
            )
            if runs and first_at(client, runs[0], args.threshold) is not None:
                break  # it walks
    finally:  # it walks, or the benchmark itself stops: the run ends KILLED, checkpointed
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            process.wait(timeout=120)
    experiment = client.get_experiment_by_name(EXPERIMENT)
    runs = experiment and client.search_runs(
        [experiment.experiment_id], f"tags.`walkers.job_key` = '{key}'", max_results=1
    )
    if not runs:
        raise SystemExit(f"error: the run of {key} did not start: {' '.join(command)}")
    return first_at(client, runs[0], args.threshold)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", default="1,8", help="algo.num_envs of each configuration")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--budget", type=int, default=500_000, help="env steps at most")
    parser.add_argument("--threshold", type=float, default=3000.0)
    parser.add_argument("--store", default=str(PROJECT / ".walkers/measure/time_to_walk.db"))
    parser.add_argument("overrides", nargs="*", help="more walkers.train overrides")
    args = parser.parse_args()
    Path(args.store).parent.mkdir(parents=True, exist_ok=True)
    uri = f"sqlite:///{Path(args.store).resolve()}"
    configurations = [int(n) for n in args.envs.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    results: dict[int, dict[int, tuple[float, int] | None]] = {n: {} for n in configurations}
    for seed in seeds:
        for n in configurations:
            results[n][seed] = train_until(args, n, seed, uri)
            print(f"num_envs={n} seed={seed}: {results[n][seed]}", flush=True)

    def median_minutes(n: int) -> float:
        return statistics.median(r[0] / 60 if r else math.inf for r in results[n].values())

    base = median_minutes(configurations[0])
    print(
        f"\nPPO on Walker2d-v5, time to the first evaluation >= {args.threshold:,.0f} "
        f"(budget {args.budget:,} env steps; store {args.store})"
    )
    print("| algo.num_envs | " + " | ".join(f"seed {s}: min (steps)" for s in seeds)
          + " | median min | ratio |")  # fmt: skip
    print("|---|" + "---|" * len(seeds) + "---|---|")
    for n in configurations:
        cells = [
            f"{r[0] / 60:.1f} ({r[1]:,})" if r else "-" for r in (results[n][s] for s in seeds)
        ]
        median = median_minutes(n)
        print(f"| {n} | " + " | ".join(cells) + f" | {median:.1f} | {median / base:.2f} |")


if __name__ == "__main__":
    main()
