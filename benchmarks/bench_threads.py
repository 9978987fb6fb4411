"""Torch's threads on the CPU: the learning phase through ``walkers.train`` itself, idle and with
one core busy, per thread setting.

    make bench-threads          # or: .venv/bin/python benchmarks/bench_threads.py --reps 2

Each contender is a real ``python -m walkers.train`` (its books, MLflow on a sqlite store in a
temporary folder) of ``--algos`` on Walker2d-v5 with a short warm-up; its learning-phase rate is
the median of the ``perf/sps`` it logged (env steps/s since the previous log) once learning had
run for one log window. Settings: ``torch_threads`` 1, 2 and all cores (``null``: torch's own
default), each also with OpenMP told not to spin (``OMP_WAIT_POLICY=PASSIVE``), and walkers'
default (``auto``, whatever ``conf/train.yaml`` says today), and for TD3 and SAC one thread with
the whole update compiled (``algo.compile=true``), where the CPU multiplies bfloat16 natively
also with ``algo.precision=bf16``. Conditions: ``idle`` (nothing else
of ours runs) and ``1 core busy`` (a plain Python busy loop at normal priority for the whole
measurement, as a laptop's browser or a second job). Contenders take turns within a condition,
so noise hits all alike; the table gives each one's median and its ratio to the best setting in
that condition. A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from mlflow.tracking import MlflowClient
from rounds import alternate

from walkers.agents.base import cpu_has_native_bf16

#: Per algorithm: the warm-up (env steps before updates) and the budget of a measured run.
RUNS = {
    "td3": ("algo.learning_starts=1000", 3000),
    "sac": ("algo.learning_starts=1000", 3000),
    "ppo": ("", 10240),  # five rollouts of 2048 steps, each with its update
}
LOG_EVERY = {"td3": 250, "sac": 250, "ppo": 2048}


#: the algorithms whose whole update ``algo.compile=true`` compiles on the CPU
COMPILED = ("td3", "sac")


def settings(cores: int, algo: str) -> dict[str, tuple[str, dict]]:
    """Name -> (overrides: torch_threads and others, extra environment)."""
    passive = {"OMP_WAIT_POLICY": "PASSIVE"}
    rows = {
        "default (as conf/train.yaml)": ("", {}),
        "1 thread": ("torch_threads=1", {}),
        "1 thread, passive": ("torch_threads=1", passive),
    }
    if algo in COMPILED:  # the same thread, the whole update compiled (an arm of its own)
        rows["1 thread, algo.compile=true"] = ("torch_threads=1 algo.compile=true", {})
        if cpu_has_native_bf16():  # and its matmuls in bfloat16 (another arm)
            bf16 = "torch_threads=1 algo.compile=true algo.precision=bf16"
            rows["1 thread, algo.compile=true algo.precision=bf16"] = (bf16, {})
    for n in sorted({2, cores}):
        name = "all cores" if n == cores else f"{n} threads"
        rows[f"{name} ({n})"] = (f"torch_threads={n}", {})
        rows[f"{name} ({n}), passive"] = (f"torch_threads={n}", passive)
    return rows


def learning_rate(algo: str, threads: str, env: dict, folder: Path) -> float:
    """One run's median env steps/s over its learning phase (after its first learning window)."""
    warmup, total = RUNS[algo]
    store = folder / f"{len(list(folder.iterdir()))}.db"
    args = [
        f"algo={algo}", "env=walker2d", f"total_steps={total}", f"eval_every={total}",
        "eval_episodes=1", f"checkpoint_every={total}", f"log_every={LOG_EVERY[algo]}",
        "progress=false", f"tracking.uri=sqlite:///{store}", f"work_dir={folder / 'work'}",
        "tracking.system_metrics=false", *filter(None, (warmup, *threads.split())),
    ]  # fmt: skip
    run_env = {**os.environ, **env}
    run_env.pop("MLFLOW_TRACKING_URI", None)
    subprocess.run(
        [sys.executable, "-m", "walkers.train", *args], cwd=folder, env=run_env, check=True,
        capture_output=True, timeout=1800,
    )  # fmt: skip
    client = MlflowClient(f"sqlite:///{store}")
    (run,) = client.search_runs([e.experiment_id for e in client.search_experiments()])
    start = int(warmup.split("=")[1]) + LOG_EVERY[algo] if warmup else 2 * LOG_EVERY[algo]
    rates = [m.value for m in client.get_metric_history(run.info.run_id, "perf/sps")
             if m.step > start]  # fmt: skip
    return statistics.median(rates)


@contextlib.contextmanager
def busy_core(on: bool):
    """A Python busy loop at normal priority on one core while the block runs."""
    if not on:
        yield
        return
    loop = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield
    finally:
        loop.kill()
        loop.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", default="td3", help="comma-separated: td3, sac, ppo")
    parser.add_argument("--reps", type=int, default=2)
    parser.add_argument("--only", default="", help="run only the settings whose name has this")
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    print(f"{cores} cores; env steps/s in the learning phase, median of {args.reps} runs each")
    for algo in args.algos.split(","):
        rows = {k: v for k, v in settings(cores, algo).items() if args.only in k}
        table = {}
        for condition, busy in (("idle", False), ("1 core busy", True)):
            with tempfile.TemporaryDirectory() as tmp, busy_core(busy):

                def measure(setting, folder=Path(tmp), algo=algo):
                    return learning_rate(algo, *setting, folder)

                table[condition] = alternate(rows, measure, args.reps)
        best = {c: max(statistics.median(v) for v in t.values()) for c, t in table.items()}
        print(f"\n{algo.upper()} on Walker2d-v5")
        print(f"| setting | {' | '.join(f'{c} (ratio to best)' for c in table)} |")
        print(f"|---|{'---|' * len(table)}")
        for name in rows:
            cells = [
                f"{statistics.median(t[name]):.0f} ({statistics.median(t[name]) / best[c]:.2f})"
                for c, t in table.items()
            ]
            print(f"| {name} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
