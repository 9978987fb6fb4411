"""Where a learning step of ``walkers.train`` goes on the CPU: TD3 on Walker2d-v5, one thread.

    make bench-profile       # or: .venv/bin/python benchmarks/profile_step.py [--algo sac]

The real path: ``python -m walkers.train algo=td3 env=walker2d`` in this process (its books and
MLflow, on a temporary store), its learning phase under ``torch.profiler``. Each piece of a
step is wrapped in a profiler range where the training calls it: acting, the env step, writing
the transition, sampling the batch, the losses' forward passes, the backward passes, the
optimizer steps, the non-finite guard and health counters, the target updates, and the books
(per-step records, the progress bar). Every aten op's own time counts for the innermost range
around it, except matrix products, which count as ``matmuls`` wherever they run; what no op
and no range accounts for (Python between the ranges) is ``the loop itself``. The profiler adds
its own cost, mostly to the many small ops: the table gives the profiled and unprofiled step
times side by side. A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import gymnasium as gym
import torch
from omegaconf import OmegaConf
from torch.profiler import ProfilerActivity, profile, record_function

from walkers import CONF_DIR
from walkers.training import loops

MATMULS = {"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::matmul"}
#: profiler range -> the row it counts for
ROWS = {
    "act": "acting (the policy's forward)",
    "env": "env step (MuJoCo)",
    "observe": "replay: writing the transition",
    "sample": "replay: sampling the batch",
    "losses": "losses' forward passes (not matmuls)",
    "backward": "backward passes (not matmuls)",
    "optimizer": "Adam steps, zero_grad",
    "guard": "non-finite guard, health counters",
    "targets": "target networks (soft updates)",
    "books": "books: per-step records, progress bar",
}


def ranged(name: str, fn):
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with record_function(f"step::{name}"):
            return fn(*args, **kwargs)

    return wrapped


@contextlib.contextmanager
def ranges(algo: str):
    """Every piece of the step wrapped in its range, where the training calls it."""
    target = OmegaConf.load(CONF_DIR / "algo" / f"{algo}.yaml")["_target_"]
    module_name, class_name = target.rsplit(".", 1)
    module = importlib.import_module(module_name)
    cls = getattr(module, class_name)
    patches = [
        (cls, "act", "act"),
        (gym.Wrapper, "step", "env"),
        (cls, "observe", "observe"),
        (cls, "sample", "sample"),
        (torch.Tensor, "backward", "backward"),
        (torch.optim.Adam, "step", "optimizer"),
        (torch.optim.Adam, "zero_grad", "optimizer"),
        (cls, "record_health", "guard"),
        (module, "skip_nonfinite", "guard"),
        (module, "soft_update", "targets"),
        (loops, "_after_step", "books"),
        (loops.RunBook, "record_episode", "books"),
    ]
    patches += [(cls, name, "losses") for name in cls.compiled_losses if hasattr(cls, name)]
    saved = []
    for owner, attr, name in patches:
        if hasattr(owner, attr):
            saved.append((owner, attr, owner.__dict__.get(attr)))
            setattr(owner, attr, ranged(name, getattr(owner, attr)))
    try:
        yield
    finally:
        for owner, attr, original in reversed(saved):
            if original is None:
                delattr(owner, attr)
            else:
                setattr(owner, attr, original)


def split(prof, steps: int, wall_ms: float) -> dict[str, float]:
    """ms per step in each row: aten ops' own time to their innermost range (matmuls apart),
    ranges' own time (Python inside them) to themselves, the rest to the loop."""
    rows: dict[str, float] = defaultdict(float)
    for event in prof.events():
        own = event.self_cpu_time_total / 1e3 / steps
        if event.name in MATMULS:
            rows["matmuls (forward and backward)"] += own
            continue
        node = event
        while node is not None and not node.name.startswith("step::"):
            node = node.cpu_parent
        if node is not None:
            rows[ROWS[node.name[len("step::") :]]] += own
    rows["the loop itself (Python between the pieces)"] = wall_ms - sum(rows.values())
    return dict(rows)


def train(algo: str, steps: int, store: Path, profiled: bool) -> tuple[float, object]:
    """The learning phase of a real run: ms per step over its last ``steps`` steps."""
    warmup = 1_000  # random actions, then learning from the next step on
    total = warmup + 200 + steps + 1  # the last step's evaluation comes after the window
    window = {}

    def timed(fn):
        @functools.wraps(fn)
        def step(agent, env, obs, losses):
            n = window.setdefault("n", 0)
            window["n"] = n + 1
            if n == warmup + 200:  # compiled, allocations warm: the window opens
                window["start"] = time.perf_counter()
                if profiled:
                    window["prof"] = profile(activities=[ProfilerActivity.CPU]).__enter__()
            if n == warmup + 200 + steps:  # before the last step and its evaluation
                window["ms"] = (time.perf_counter() - window["start"]) * 1e3 / steps
                if profiled:
                    window["prof"].__exit__(None, None, None)
            return fn(agent, env, obs, losses)

        return step

    original = loops.online_step
    loops.online_step = timed(original)
    argv = sys.argv
    sys.argv = [
        "walkers.train", f"algo={algo}", "env=walker2d", f"total_steps={total}",
        f"algo.learning_starts={warmup}", f"eval_every={total}", f"checkpoint_every={total}",
        "algo.buffer_size=100000", "progress=false", "torch_threads=1",
        f"tracking.uri=sqlite:///{store}/mlflow.db", f"work_dir={store}/work",
        f"hydra.run.dir={store}/outputs", "hydra/job_logging=disabled",
    ]  # fmt: skip
    try:
        from walkers.train import main

        with contextlib.suppress(SystemExit):
            main()
    finally:
        loops.online_step, sys.argv = original, argv
    return window["ms"], window.get("prof")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", default="td3", help="an off-policy algorithm (td3, sac, ...)")
    parser.add_argument("--steps", type=int, default=1_500, help="learning steps measured")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="walkers-profile-") as tmp:
        os.chdir(tmp)
        plain_ms, _ = train(args.algo, args.steps, Path(tmp) / "plain", profiled=False)
        with ranges(args.algo):
            profiled_ms, prof = train(args.algo, args.steps, Path(tmp) / "profiled", True)
    rows = split(prof, args.steps, profiled_ms)
    print(
        f"\n{args.algo.upper()} on Walker2d-v5 through walkers.train, learning phase, 1 thread, "
        f"{args.steps} steps: {plain_ms:.2f} ms a step unprofiled ({1e3 / plain_ms:.0f} env "
        f"steps/s), {profiled_ms:.2f} ms profiled"
    )
    print("| piece of the step | ms/step (profiled) | share |")
    print("|---|---|---|")
    for row, ms in sorted(rows.items(), key=lambda kv: -kv[1]):
        print(f"| {row} | {ms:.3f} | {ms / profiled_ms:.0%} |")


if __name__ == "__main__":
    main()
