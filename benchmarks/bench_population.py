"""What a population's lockstep step costs per member, through ``walkers.train`` itself.

    make bench-population                                   # warm-up phase, K = 1, 4, 16, CPU
    .venv/bin/python benchmarks/bench_population.py --split # and where a step's host time goes
    .venv/bin/python benchmarks/bench_population.py --device cuda --phase learning \
        --populations 1,5,16
    git worktree add ../main-before HEAD~3 && make bench-population ARGS="--against ../main-before"

**The rate** is a real ``walkers.train algo=td3 env=walker2d population=K``: the entry point's
own ``train`` (what ``python -m walkers.train`` calls once Hydra has composed the config) with
its books, its MLflow store in a temporary folder, its evaluation and checkpoints. Each row's
round runs in a fresh process, the rows taking turns over ``--reps`` rounds. A run logs
``perf/sps`` (lockstep steps a second since its last log) every ``--log-every`` steps; the row
is the median of those after the first, so start-up and the closing evaluation are left out.
``--phase warmup`` (the default) sets ``algo.learning_starts`` to the budget: random actions,
no updates, so what is left beside the env is the loop's own cost. ``--phase learning`` starts
updating after 1,000 steps (a GPU's question: does anything but the update cost?). In the same
process, before and after the training, the bare env step: Walker2d-v5 as walkers builds it
(``make_env``: ``RecordEpisodeStatistics`` around ``gym.make``), random actions.

**The split** (``--split``) runs the same training again in that process with a timer around
each phase of the loop, named by the code it wraps (a phase inside another counts to the outer
one): ``books`` is ``_population_books`` (episode records, step counts, each book's after_step
when due), and ``the step's own lines`` the rest of :class:`walkers.training.loops.Lockstep`'s
step. The timers add about a microsecond a call: read the split beside the rate, not instead of it.

A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENV = "walker2d"
WARMUP_LEARNING_STARTS = 1_000  # --phase learning: updates from here on


def train_overrides(k: int, steps: int, phase: str, device: str, log_every: int, uri: str):
    """The ``walkers.train`` command line of one row (TD3 on Walker2d-v5, one torch thread)."""
    learning_starts = steps if phase == "warmup" else WARMUP_LEARNING_STARTS
    return [
        "algo=td3",
        f"env={ENV}",
        f"population={k}",
        f"total_steps={steps}",
        f"algo.learning_starts={learning_starts}",
        f"eval_every={steps}",
        "eval_episodes=1",
        f"checkpoint_every={steps}",
        f"log_every={log_every}",
        f"device={device}",
        "torch_threads=1",
        "progress=false",
        f"tracking.uri={uri}",
        f"tracking.experiment=bench_population_k{k}",
    ]


def train_in_this_process(k: int, args, folder: Path) -> float:
    """Lockstep steps a second of ``walkers.train ... population=k`` run here (the entry
    point's own ``train`` on the composed config; the median of its logged ``perf/sps`` past
    the first log)."""
    import torch
    from hydra import compose, initialize_config_dir
    from mlflow.tracking import MlflowClient

    from walkers import CONF_DIR
    from walkers.train import train

    uri = f"sqlite:///{folder / f'k{k}.db'}"
    overrides = train_overrides(k, args.steps, args.phase, args.device, args.log_every, uri)
    os.environ["WALKERS_WORK_DIR"] = str(folder / "work")
    with initialize_config_dir(config_dir=str(CONF_DIR)):
        cfg = compose(config_name="train", overrides=overrides)
    torch.set_num_threads(1)
    train(cfg, overrides)
    client = MlflowClient(uri)
    (experiment,) = [e for e in client.search_experiments() if e.name.endswith(f"_k{k}")]
    run = client.search_runs([experiment.experiment_id], order_by=["start_time DESC"])[0]
    history = client.get_metric_history(run.info.run_id, "perf/sps")
    rates = [m.value for m in sorted(history, key=lambda m: m.step)][1:]
    return statistics.median(rates)


def bare_env_step_us(steps: int) -> float:
    """Microseconds per step of one Walker2d-v5 as walkers builds it, random actions."""
    from walkers.training.envs import make_env

    env = make_env({"id": "Walker2d-v5", "max_episode_steps": 1000})
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(steps, env.action_space.shape[0])).astype(np.float32)
    env.reset(seed=0)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return elapsed / steps * 1e6


def envs_in_turn_us(k: int, steps: int) -> float:
    """Microseconds per env step of ``k`` such envs stepped in turn, random actions (no agent,
    no books): what K members' envs cost by themselves, their caches shared."""
    from walkers.training.envs import make_env

    envs = [make_env({"id": "Walker2d-v5", "max_episode_steps": 1000}) for _ in range(k)]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(steps // k + 1, k, envs[0].action_space.shape[0]))
    actions = actions.astype(np.float32)
    for i, env in enumerate(envs):
        env.reset(seed=i)
    start = time.perf_counter()
    for step_actions in actions:
        for env, action in zip(envs, step_actions, strict=True):
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                env.reset()
    elapsed = time.perf_counter() - start
    for env in envs:
        env.close()
    return elapsed / (len(actions) * k) * 1e6


def worker(args) -> None:
    """One row's round in a fresh process: the bare env step and the K envs in turn, the
    training, both again (the same process, so the same caches and clocks), then, with
    ``--split``, the training again with its phases timed; one JSON line."""
    k = args.worker
    with tempfile.TemporaryDirectory(prefix="bench-population-") as tmp:
        bare, in_turn = [bare_env_step_us(args.steps)], [envs_in_turn_us(k, args.steps * k)]
        rate = train_in_this_process(k, args, Path(tmp))
        bare.append(bare_env_step_us(args.steps))
        in_turn.append(envs_in_turn_us(k, args.steps * k))
    row = {
        "k": k,
        "member_step_us": 1e6 / (rate * k),
        "bare_us": statistics.mean(bare),
        "in_turn_us": statistics.mean(in_turn),
    }
    if args.split and k > 1:
        row["split"] = split(k, args)
    print("ROW " + json.dumps(row), flush=True)


def rounds(args) -> dict[str, list[dict]]:
    """``--reps`` rounds of every row, each row a fresh process, the rows taking turns; with
    ``--against``, each K also on that checkout (its ``walkers`` first on the path)."""
    trees = {"": None} | ({f" ({args.against})": args.against} if args.against else {})
    rows: dict[str, list[dict]] = {}
    passed = [f"--{name.replace('_', '-')}={getattr(args, name)}" for name in PASSED]
    for _ in range(args.reps):
        for k in [int(k) for k in args.populations.split(",")]:
            for label, tree in trees.items():
                command = [sys.executable, __file__, f"--worker={k}", *passed]
                command += ["--split"] if args.split and tree is None else []
                env = os.environ | ({"PYTHONPATH": str(Path(tree).resolve())} if tree else {})
                out = subprocess.run(
                    command, check=True, capture_output=True, text=True, env=env
                ).stdout
                (line,) = [x for x in out.splitlines() if x.startswith("ROW ")]
                rows.setdefault(f"{k}{label}", []).append(json.loads(line[4:]))
    return rows


#: the options a worker is handed on
PASSED = ("steps", "log_every", "phase", "device")


def rate_table(args, rows: dict[str, list[dict]]) -> None:
    print(
        f"\nTD3 on Walker2d-v5 through walkers.train, {args.phase} phase, {args.device}, one torch "
        f"thread, {args.reps} rounds x {args.steps} lockstep steps (medians; the bare step and "
        "the K envs in turn timed in the same process, before and after the training)"
    )
    print(
        "| population | µs per member-step | bare env step µs | above it | K envs in turn µs "
        "| above them | env steps/s |"
    )
    print("|---|---|---|---|---|---|---|")

    def median(runs, f):
        return statistics.median(f(r) for r in runs)

    for label, runs in rows.items():
        us = median(runs, lambda r: r["member_step_us"])
        bare = median(runs, lambda r: r["bare_us"])
        in_turn = median(runs, lambda r: r["in_turn_us"])
        above = median(runs, lambda r: r["member_step_us"] - r["bare_us"])
        above_turn = median(runs, lambda r: r["member_step_us"] - r["in_turn_us"])
        print(
            f"| {label} | {us:.0f} | {bare:.0f} | {above:+.0f} | {in_turn:.0f} | {above_turn:+.0f} "
            f"| {1e6 / us:,.0f} |"
        )


# --- the split: the same training in this process, each phase timed ------------------------------
class PhaseClock:
    """Seconds per phase of each lockstep step; a phase called inside another counts to it."""

    def __init__(self):
        self.steps: list[dict[str, float]] = []
        self.current: dict[str, float] = {}
        self.depth = 0

    def wrap(self, owner, name: str, phase: str) -> None:
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*a, **kw):
            if self.depth:
                return original(*a, **kw)
            self.depth += 1
            start = time.perf_counter()
            try:
                return original(*a, **kw)
            finally:
                self.depth -= 1
                self.current[phase] = self.current.get(phase, 0.0) + time.perf_counter() - start

        setattr(owner, name, timed)

    def wrap_step(self, owner, name: str) -> None:
        """``owner.name`` starts a new lockstep step (its own lines are ``the step's own``)."""
        original = getattr(owner, name)

        @functools.wraps(original)
        def step(*a, **kw):
            self.current = {}
            self.steps.append(self.current)
            start = time.perf_counter()
            try:
                return original(*a, **kw)
            finally:
                self.current["step"] = time.perf_counter() - start

        setattr(owner, name, step)

    def per_member_us(self, k: int, skip: int) -> dict[str, float]:
        """Mean microseconds per member-step of each phase, past the first ``skip`` steps and
        without the last (its evaluation and checkpoint)."""
        steps = self.steps[skip:-1]
        phases = sorted({p for s in steps for p in s} - {"step", "books"})

        def mean(phase: str) -> float:
            return sum(s.get(phase, 0.0) for s in steps) / len(steps) / k * 1e6

        out = {phase: mean(phase) for phase in phases}
        out["the step's own lines"] = mean("step") - sum(out.values())
        out["books"] = mean("books")
        out["total"] = mean("step") + out["books"]
        return out


#: What the split times: (module, attribute path, phase); ``None``: the lockstep step itself.
PHASES = [
    ("walkers.training.loops", "Lockstep.step", None),
    ("walkers.training.loops", "_population_books", "books"),
    ("gymnasium.vector", "SyncVectorEnv.step", "env stepping (the vector env)"),
    ("walkers.agents.common.actor_critic", "ActorCritic.act_population", "acting"),
    ("walkers.agents.common.actor_critic", "ActorCritic.store_steps", "storing"),
    ("walkers.agents.td3", "TD3.update", "update"),
    ("walkers.agents.common.capture", "CapturedUpdate.__call__", "update"),
]


def split(k: int, args) -> dict[str, float]:
    """The same training as the row's, its phases timed (:data:`PHASES`)."""
    import importlib

    clock, originals = PhaseClock(), []
    for module, path, phase in PHASES:
        owner = importlib.import_module(module)
        *parents, name = path.split(".")
        for parent in parents:
            owner = getattr(owner, parent)
        originals.append((owner, name, getattr(owner, name)))
        if phase is None:
            clock.wrap_step(owner, name)
        else:
            clock.wrap(owner, name, phase)
    try:
        with tempfile.TemporaryDirectory(prefix="bench-population-split-") as tmp:
            train_in_this_process(k, args, Path(tmp))
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)
    return clock.per_member_us(k, skip=min(100, args.steps // 10))


def split_table(args, rows: dict[str, list[dict]]) -> None:
    splits = {k: [r["split"] for r in runs] for k, runs in rows.items() if runs[0].get("split")}
    if not splits:
        return
    phases = list(next(iter(splits.values()))[0])
    print(
        f"\nWhere a lockstep step's host time goes, µs per member-step ({args.phase}, "
        f"{args.device}; medians of {args.reps} rounds; K = 1 trains by the single-run loop)"
    )
    print("| phase | " + " | ".join(f"K = {k}" for k in splits) + " |")
    print("|---|" + "---|" * len(splits))
    for phase in phases:
        cells = [statistics.median(s[phase] for s in runs) for runs in splits.values()]
        print(f"| {phase} | " + " | ".join(f"{c:.1f}" for c in cells) + " |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--populations", default="1,4,16", help="the K of each row")
    parser.add_argument("--steps", type=int, default=3_000, help="lockstep steps a run")
    parser.add_argument("--log-every", type=int, default=250, help="steps between perf/sps logs")
    parser.add_argument("--reps", type=int, default=2, help="rounds")
    parser.add_argument("--phase", choices=("warmup", "learning"), default="warmup")
    parser.add_argument("--device", default="cpu", help="cpu | cuda")
    parser.add_argument("--split", action="store_true", help="also the split by phase")
    parser.add_argument(
        "--against", help="another checkout (e.g. a git worktree of main) to run each K on too"
    )
    parser.add_argument("--worker", type=int, help=argparse.SUPPRESS)  # one row's round
    args = parser.parse_args(argv)
    if args.worker:
        worker(args)
        return
    rows = rounds(args)
    rate_table(args, rows)
    split_table(args, rows)


if __name__ == "__main__":
    main()
