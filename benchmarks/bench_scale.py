"""A seed study on one machine's launchers: joblib against a Ray cluster of 1 and 2 worker nodes.

    make bench-scale                # or: .venv/bin/python benchmarks/bench_scale.py --seeds 4

The same multirun (TD3 on Pendulum, 64-64, ``--seeds`` seeds x ``--steps`` env steps, one thread
per job) through ``hydra/launcher=joblib`` (2 jobs at a time) and ``hydra/launcher=ray_cluster`` on
a Ray cluster started here on loopback with 1 node of 1 CPU, then 2 such nodes (so at most 1 and 2
jobs run at once). For each: the wall time of the command, the aggregate env steps/s (all seeds'
steps over the wall time), the mean job's own throughput (``perf/sps``), and the overhead per job:
from the command's start to the first job's MLflow run (launcher start-up, process and imports),
and the wall time not spent training (wall - jobs' training time / parallel jobs).

Then, on paper: the study's real jobs (2 algorithms x 5 seeds x 1M Walker2d steps; a 40-trial
sweep of 300k steps) with N workers, from a one-thread Walker2d job's rate (``--walker2d-sps``:
half of `make bench-throughput`'s aggregate for 2 one-thread processes) and the overhead
measured here. A benchmark, not a test.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mlflow.tracking import MlflowClient

RAY = str(Path(sys.executable).with_name("ray"))
ROOT = Path(__file__).resolve().parents[1]


def run_study(launcher: list[str], seeds: int, steps: int, folder: Path) -> dict:
    """One seed study through ``launcher``; its figures from the command and its MLflow runs."""
    store = f"sqlite:///{folder / 'mlflow.db'}"
    command = [
        sys.executable, "-m", "walkers.train", "-m", "algo=td3", "env=pendulum",
        f"seed=range({seeds})", "algo.hidden_sizes=[64,64]", f"total_steps={steps}",
        f"eval_every={steps // 2}", "eval_episodes=2", f"checkpoint_every={steps}",
        "progress=false", "torch_threads=1", "tracking.system_metrics=false",
        f"tracking.uri={store}", f"work_dir={folder / '.walkers'}",
        f"hydra.sweep.dir={folder / 'multirun'}", *launcher,
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    start = time.time()
    done = subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True)
    wall = time.time() - start
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-3000:])
    client = MlflowClient(store)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    first_start = min(r.info.start_time for r in runs) / 1000
    training = sum((r.info.end_time - r.info.start_time) / 1000 for r in runs)
    return {
        "wall": wall,
        "aggregate": seeds * steps / wall,
        "job_sps": sum(r.data.metrics["perf/sps"] for r in runs) / len(runs),
        "first_job": first_start - start,
        "training": training,
    }


class RayCluster:
    """``ray start`` a head (and more nodes) on loopback, 1 CPU each; ``ray stop`` on exit."""

    def __init__(self, folder: Path):
        self.folder, self.port = folder, 6400 + os.getpid() % 500

    def start(self, nodes: int) -> str:
        env = {**os.environ, "OMP_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0"}
        cpus = ["--num-cpus", "1", "--disable-usage-stats"]
        head = [RAY, "start", "--head", f"--port={self.port}", "--include-dashboard=false", *cpus]
        subprocess.run(head, cwd=self.folder, env=env, check=True, capture_output=True)
        for _ in range(nodes - 1):
            node = [RAY, "start", f"--address=127.0.0.1:{self.port}", *cpus]
            subprocess.run(node, cwd=self.folder, env=env, check=True, capture_output=True)
        return f"127.0.0.1:{self.port}"

    @staticmethod
    def stop() -> None:
        subprocess.run([RAY, "stop", "--force"], capture_output=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=4000, help="env steps per seed")
    parser.add_argument("--walker2d-sps", type=float, default=80.0,
                        help="a one-thread TD3 Walker2d job's env steps/s (make bench-throughput: "
                        "half its '2 one-thread processes' aggregate)")  # fmt: skip
    args = parser.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, workers in (("joblib, 2 jobs", 0), ("Ray, 1 worker", 1), ("Ray, 2 workers", 2)):
            folder = Path(tmp) / name.replace(",", "").replace(" ", "_")
            folder.mkdir()
            if workers == 0:
                launcher = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]
                rows[name] = run_study(launcher, args.seeds, args.steps, folder) | {"parallel": 2}
                continue
            cluster = RayCluster(folder)
            try:
                address = cluster.start(workers)
                launcher = [
                    "hydra/launcher=ray_cluster",
                    f"hydra.launcher.ray.init.address={address}",
                ]
                rows[name] = run_study(launcher, args.seeds, args.steps, folder)
                rows[name]["parallel"] = workers
            finally:
                cluster.stop()
    print(f"\nSeed study: TD3 Pendulum 64-64, {args.seeds} seeds x {args.steps} env steps, "
          f"{os.cpu_count()} cores\n")  # fmt: skip
    print("| launcher | wall s | aggregate env steps/s | job env steps/s | to first job s | "
          "overhead per job s |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for name, r in rows.items():
        waves = math.ceil(args.seeds / r["parallel"])
        overhead = (r["wall"] - r["training"] / r["parallel"]) / waves
        r["overhead"] = overhead
        print(f"| {name} | {r['wall']:.1f} | {r['aggregate']:.0f} | {r['job_sps']:.0f} | "
              f"{r['first_job']:.1f} | {overhead:.1f} |")  # fmt: skip

    overhead = rows["Ray, 2 workers"]["overhead"]
    print(f"\nOn paper: a Walker2d job at {args.walker2d_sps:.0f} env steps/s (one job per worker "
          f"of 1-2 cores), plus {overhead:.0f} s per job\n")  # fmt: skip
    print("| workers | study: 2 algos x 5 seeds x 1M steps | sweep: 40 trials x 300k steps |")
    print("|---|---|---|")
    for n in (1, 2, 5, 10, 20, 40):
        study = math.ceil(10 / n) * (1_000_000 / args.walker2d_sps + overhead) / 3600
        sweep = math.ceil(40 / n) * (300_000 / args.walker2d_sps + overhead) / 3600
        print(f"| {n} | {study:.1f} h | {sweep:.1f} h (no pruning) |")


if __name__ == "__main__":
    main()
