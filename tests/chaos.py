"""`make chaos`: the fault matrix. Every fault of :data:`tests.cluster_kit.FAULTS`, several times.

    make chaos                                   # 3 repetitions of every fault, seed 0
    make chaos ARGS="--reps 5 --seed 1 --only 'PostgreSQL down'"

One PostgreSQL (its study database takes a password, given to every command by reference), one
MLflow server and one Ray cluster (a head and a worker node on loopback) serve the whole matrix.
Each cell is a 2-trial sweep of TD3 on Pendulum on the cluster with its fault injected at a time
drawn from a generator seeded by ``--seed``, then checked: 0 runs RUNNING, 0 trials RUNNING,
every trial accounted for, no evaluation step logged twice, the password in no file (sweep and
job folders, Ray's session logs, the server's artifacts and log), no console line and no MLflow
param or tag, and ``walkers.compare`` over the experiment works. Prints the matrix (fault x
repetition: passed, or what broke) and exits 1 if any cell broke. Minutes per cell on 2 cores.
"""

from __future__ import annotations

import argparse
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

from tests.cluster_kit import FAULTS, LocalRay, run_fault, start_stack
from walkers.tuning.studies import STORAGE_ENV


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=3, help="repetitions of every fault")
    parser.add_argument("--seed", type=int, default=0, help="seeds the injection times")
    parser.add_argument("--only", action="append", choices=list(FAULTS), help="these faults")
    parser.add_argument("--keep", action="store_true", help="keep the stores, sweeps and logs")
    args = parser.parse_args(argv)
    faults = args.only or list(FAULTS)
    rng = random.Random(args.seed)
    folder = Path(tempfile.mkdtemp(prefix="chaos-"))
    stack = start_stack(folder / "stack")
    ray = LocalRay(nodes=2, env={STORAGE_ENV: stack.optuna_url}).start()
    cells: dict[str, list[str]] = {}
    try:
        for fault in faults:
            for rep in range(args.reps):
                name = f"chaos_{len(cells)}_{rep}_{fault[:12]}".replace(" ", "_")
                started = time.monotonic()
                result = run_fault(stack, ray, fault, name, folder / name, rng)
                seconds = time.monotonic() - started
                cell = "passed" if not result.broken else "; ".join(result.broken)[:300]
                cells.setdefault(fault, []).append(cell)
                print(f"{fault} #{rep + 1}: {result.done} -> {cell} ({seconds:.0f} s)", flush=True)
    finally:
        ray.stop()
        stack.stop()
        if args.keep:
            print(f"stores, sweeps and logs kept in {folder}")
        else:
            shutil.rmtree(folder, ignore_errors=True)
    print()
    print("| fault | " + " | ".join(f"rep {i + 1}" for i in range(args.reps)) + " |")
    print("|---|" + "---|" * args.reps)
    for fault, row in cells.items():
        print(f"| {fault} | " + " | ".join(row) + " |")
    broken = sum(cell != "passed" for row in cells.values() for cell in row)
    total = sum(len(row) for row in cells.values())
    print(f"\n{total - broken} passed, {broken} failed")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
