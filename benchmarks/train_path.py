"""The files and classes of ``walkers/`` that one ``python -m walkers.train`` passes through.

    python benchmarks/train_path.py [--list] [override ...]    (make bench-path)

Runs the real command in this process (a short TD3 on Walker2d-v5 by default: 2,000 steps,
updates from 1,000, one evaluation episode, a temporary store and work folder) with a profile
hook that notes every Python function of ``walkers/`` called (not a module's or a class's body,
run by an import), then prints how many files and
classes that is (a class counts when one of its methods ran). What a reader meets before
changing a loop: the measure of docs/architecture.md's training path.
"""

from __future__ import annotations

import argparse
import inspect
import runpy
import sys
import tempfile
import threading
from pathlib import Path

import walkers

PACKAGE = str(Path(walkers.__file__).parent)
SHORT_TD3 = [
    "algo=td3",
    "env=walker2d",
    "total_steps=2000",
    "algo.learning_starts=1000",
    "eval_every=1000",
    "eval_episodes=1",
    "checkpoint_every=1000",
    "progress=false",
]


def passed_through(argv: list[str]) -> tuple[set[str], set[str]]:
    """Run ``python -m walkers.train *argv`` here; the files and ``file:Class`` it called into."""
    files, classes = set(), set()

    def note(frame, event, _arg):
        if event != "call":
            return
        code = frame.f_code
        if not code.co_filename.startswith(PACKAGE) or not code.co_flags & inspect.CO_OPTIMIZED:
            return  # another package's, or a module's or a class's body (run by an import)
        if code.co_name.startswith("<"):
            return  # a comprehension or a lambda: its function counts
        file = code.co_filename[len(PACKAGE) - len("walkers") :]
        files.add(file)
        head = code.co_qualname.split(".")[0]
        if isinstance(frame.f_globals.get(head), type) and head != code.co_qualname:
            classes.add(f"{file}:{head}")

    sys.argv = ["walkers.train", *argv]
    sys.setprofile(note)
    threading.setprofile(note)
    try:
        runpy.run_module("walkers.train", run_name="__main__")
    except SystemExit as end:
        if end.code not in (0, None):
            raise
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    return files, classes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--list", action="store_true", help="list the files and classes too")
    parser.add_argument(
        "overrides", nargs="*", help="walkers.train overrides (after the TD3 run's)"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        store = [f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"work_dir={tmp}/work"]
        hydra = [f"hydra.run.dir={tmp}/outputs"]
        files, classes = passed_through([*SHORT_TD3, *store, *hydra, *args.overrides])
    print(f"\n| walkers.train {' '.join(SHORT_TD3[:2])} passes through | count |")
    print("|---|---|")
    print(f"| files of walkers/ | {len(files)} |")
    print(f"| classes of walkers/ (a method called) | {len(classes)} |")
    if args.list:
        print("\n".join(["", *sorted(files), "", *sorted(classes)]))


if __name__ == "__main__":
    main()
