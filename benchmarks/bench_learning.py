"""Learning at equal budget: walkers TD3 vs Stable-Baselines3 TD3, same hyperparameters, N seeds.

    make bench-learning                                  # Walker2d-v5, 100k steps, 5 seeds (hours)
    .venv/bin/python benchmarks/bench_learning.py --env pendulum --steps 15000 --seeds 3
    .venv/bin/python benchmarks/bench_learning.py --env Walker2d-v5 --env Hopper-v5 --seeds 3

Each seed trains once per library, libraries alternating seed by seed (machine drift hits both
alike), one training at a time with the same number of torch threads. walkers runs as a user
runs it: ``python -m walkers.train algo=td3 env=... seed=S total_steps=N
algo.learning_starts=W`` (no evaluation before the end), logged to a temporary MLflow store.
SB3's TD3 (benchmarks/sb3_td3.py) runs in its own process with every hyperparameter taken from
the same composed walkers config: the TD3 reference values (256-256, lr 3e-4, batch 256, ``W``
uniform random warm-up steps, exploration N(0, 0.1) and target noise 0.2 clipped at 0.5 of the
action half-range, policy delay 2, tau 0.005, gamma 0.99, buffer 1e6, one gradient step per env
step), trained on walkers' training env.

Both final policies are then scored here by one function, walkers' own evaluation
(``walkers.training.rollout.run_episodes``): ``--episodes`` deterministic episodes on a separate,
unshaped env, episode i starting from ``walkers.seeding.eval_start_seeds(seed)[i]`` (independent
start states per seed, the same for both libraries), returns the env's own. walkers' policy comes
from its run's ``checkpoints/last.pt`` artifact; the run's own ``final/return_mean`` is checked
against the re-evaluation. One table per env: per-seed final returns, mean ± std, IQM
(``scipy.stats.trim_mean(x, 0.25)``) with a 95% percentile-bootstrap CI over seeds
(``walkers.analysis.stats.iqm_ci``, ``scipy.stats.bootstrap``), wall time per seed (the
training process, start to exit), env steps/s of the training loop (walkers: its ``perf/sps``,
which includes its one final evaluation; SB3: ``learn()``), and the ratio walkers / SB3 of the
IQMs. Every store, checkpoint and model lives in a temporary directory, removed at the end. A
benchmark, not a test: SB3 is the ``bench`` extra (``pip install -e '.[bench]'``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from hydra import compose, initialize_config_dir
from mlflow import MlflowClient
from omegaconf import OmegaConf
from rounds import alternate

from walkers.analysis.stats import iqm_ci
from walkers.cli import CONF_DIR
from walkers.seeding import eval_start_seeds
from walkers.training import checkpoints
from walkers.training.checkpoints import agent_from_checkpoint
from walkers.training.envs import make_env
from walkers.training.rollout import run_episodes

SB3_WORKER = Path(__file__).resolve().parent / "sb3_td3.py"
EXPERIMENT = "bench_learning"
ENV_CONFIGS = {path.stem: OmegaConf.load(path).id for path in Path(CONF_DIR, "env").glob("*.yaml")}


@dataclass
class Setup:
    """One env's comparison: what both libraries train with, and where runs go."""

    env_name: str  # as given on the command line
    overrides: list[str]  # walkers.train overrides shared by both libraries (less the seed)
    env: dict  # the composed env config
    algo: dict  # the composed TD3 config: SB3 copies it
    steps: int
    episodes: int
    threads: int
    tmp: Path


@dataclass
class Result:
    """One library's one seed."""

    seed: int
    returns: np.ndarray  # final policy, one return per evaluation episode
    wall_s: float  # the training process, start to exit
    sps: float  # env steps per second of the training loop
    own_final: float | None = None  # walkers: its run's own final/return_mean


def env_overrides(name: str) -> list[str]:
    """Select ``name``: a walkers env config (conf/env/NAME.yaml), the config with that
    gymnasium id, or any other gymnasium id (on walker2d's config, with gymnasium's time limit)."""
    if name in ENV_CONFIGS:
        return [f"env={name}"]
    for config, env_id in ENV_CONFIGS.items():
        if env_id == name:
            return [f"env={config}"]
    if name in gym.registry:
        return ["env=walker2d", f"env.id={name}", "env.max_episode_steps=null"]
    raise ValueError(
        f"--env {name}: neither a walkers env config ({', '.join(sorted(ENV_CONFIGS))}) "
        "nor a registered gymnasium id"
    )


def make_setup(name: str, args: argparse.Namespace, tmp: Path) -> Setup:
    overrides = [
        "algo=td3",
        *env_overrides(name),
        f"total_steps={args.steps}",
        f"algo.learning_starts={args.warmup}",
        f"eval_episodes={args.episodes}",
        f"torch_threads={args.threads}",
        "device=cpu",
    ]
    with initialize_config_dir(config_dir=CONF_DIR):
        cfg = compose("train", overrides=overrides)
    folder = tmp / name.replace("/", "_")
    folder.mkdir()
    return Setup(
        env_name=name,
        overrides=overrides,
        env=OmegaConf.to_container(cfg.env, resolve=True),
        algo=OmegaConf.to_container(cfg.algo, resolve=True),
        steps=args.steps,
        episodes=args.episodes,
        threads=args.threads,
        tmp=folder,
    )


def run_process(cmd: list[str], folder: Path) -> float:
    """Run ``cmd`` in ``folder`` (its log there); its wall time in seconds. Exits on failure."""
    log = folder / "log.txt"
    start = time.perf_counter()
    with log.open("w") as out:
        code = subprocess.run(cmd, cwd=folder, stdout=out, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - start
    if code != 0:
        tail = "\n".join(log.read_text().splitlines()[-30:])
        raise SystemExit(f"error: {' '.join(cmd)} exited {code}:\n{tail}")
    return wall


def final_returns(policy, setup: Setup, seed: int) -> np.ndarray:
    """The one evaluation for both libraries: walkers' own (see the module docstring)."""
    env = make_env(setup.env, shaping=False)
    try:
        return run_episodes(policy, env, eval_start_seeds(seed, setup.episodes))
    finally:
        env.close()


def train_walkers(setup: Setup, seed: int) -> Result:
    """``python -m walkers.train`` with its own temporary MLflow store and work dir."""
    folder = setup.tmp / f"walkers-s{seed}"
    folder.mkdir()
    uri = f"sqlite:///{folder / 'mlflow.db'}"
    cmd = [
        *(sys.executable, "-m", "walkers.train", *setup.overrides, f"seed={seed}"),
        f"eval_every={setup.steps}",  # SB3 evaluates nothing while it learns: neither do we
        f"tracking.uri={uri}",
        f"tracking.experiment={EXPERIMENT}",
        "progress=false",
        f"work_dir={folder / 'work'}",
    ]
    wall = run_process(cmd, folder)
    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name(EXPERIMENT)
    (run,) = client.search_runs([experiment.experiment_id])
    history = client.get_metric_history(run.info.run_id, "perf/sps")
    sps = max(history, key=lambda m: (m.step, m.timestamp)).value  # the whole-run rate
    last = client.download_artifacts(run.info.run_id, "checkpoints/last.pt", str(folder))
    env = make_env(setup.env, shaping=False)
    _, agent = agent_from_checkpoint(checkpoints.load(last), env, device="cpu")
    env.close()
    returns = final_returns(agent, setup, seed)
    return Result(seed, returns, wall, sps, own_final=run.data.metrics["final/return_mean"])


def train_sb3(setup: Setup, seed: int) -> Result:
    """benchmarks/sb3_td3.py in its own process, on the same env and algo config."""
    from sb3_td3 import load_policy

    folder = setup.tmp / f"sb3-s{seed}"
    folder.mkdir()
    spec = {
        "env": setup.env,
        "algo": setup.algo,
        "seed": seed,
        "total_steps": setup.steps,
        "threads": setup.threads,
        "model_path": str(folder / "model.zip"),
    }
    spec_path = folder / "spec.json"
    spec_path.write_text(json.dumps(spec))
    wall = run_process([sys.executable, str(SB3_WORKER), str(spec_path)], folder)
    timing = json.loads(spec_path.with_suffix(".result.json").read_text())
    returns = final_returns(load_policy(folder / "model.zip"), setup, seed)
    return Result(seed, returns, wall, timing["sps"])


TRAINERS = {"walkers TD3": train_walkers, "SB3 TD3": train_sb3}


def compare(setup: Setup, seeds: list[int]) -> dict[str, list[Result]]:
    """Every seed once per library, the libraries taking turns seed by seed."""

    def measure(contender) -> Result:
        (name, train), pending = contender
        seed = next(pending)
        print(f"  {setup.env_name}: {name} seed {seed} ...", end=" ", flush=True)
        result = train(setup, seed)
        print(
            f"final return {result.returns.mean():.1f}, {result.wall_s:.0f} s, "
            f"{result.sps:.0f} env steps/s",
            flush=True,
        )
        return result

    contenders = {name: ((name, train), iter(seeds)) for name, train in TRAINERS.items()}
    return alternate(contenders, measure, reps=len(seeds))


HEADER = [
    *("library", "final return per seed", "mean ± std", "IQM [95% CI]"),
    *("wall s/seed", "env steps/s"),
]


def table_row(name: str, runs: list[Result]) -> tuple[list[str], float]:
    """One library's cells, and its IQM."""
    finals = np.array([r.returns.mean() for r in runs])
    iqm, low, high = iqm_ci([finals])
    std = finals.std(ddof=1) if len(finals) > 1 else math.nan
    cells = [
        name,
        ", ".join(f"{x:.1f}" for x in finals),
        f"{finals.mean():.1f} ± {std:.1f}",
        f"{iqm:.1f} [{low:.1f}, {high:.1f}]",
        f"{np.mean([r.wall_s for r in runs]):.0f}",
        f"{np.mean([r.sps for r in runs]):.1f}",
    ]
    return cells, iqm


def print_markdown(rows: list[list[str]]) -> None:
    """A markdown table under :data:`HEADER`: names left, numbers right."""
    widths = [max(len(row[i]) for row in [HEADER, *rows]) for i in range(len(HEADER))]
    print("| " + " | ".join(h.ljust(w) for h, w in zip(HEADER, widths, strict=True)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for name, *cells in rows:
        cells = [c.rjust(w) for c, w in zip(cells, widths[1:], strict=True)]
        print("| " + " | ".join([name.ljust(widths[0]), *cells]) + " |")


def print_table(setup: Setup, warmup: int, results: dict[str, list[Result]]) -> None:
    seeds = [r.seed for r in results["walkers TD3"]]
    print(
        f"\n{setup.env['id']}: TD3, {setup.steps} env steps ({warmup} random warm-up), "
        f"seeds {', '.join(map(str, seeds))}, {setup.threads} torch threads. Final policy, "
        f"{setup.episodes} deterministic episodes per seed on a separate env (walkers' "
        "run_episodes, start states walkers.seeding.eval_start_seeds(seed)), the env's returns"
    )
    rows, iqms = [], {}
    for name, runs in results.items():
        cells, iqms[name] = table_row(name, runs)
        rows.append(cells)
    print_markdown(rows)
    print(iqm_ratio(iqms["walkers TD3"], iqms["SB3 TD3"]))
    print(own_evaluation_check(results["walkers TD3"]))


def iqm_ratio(walkers: float, sb3: float) -> str:
    difference = f"difference {walkers - sb3:+.1f}"
    if walkers * sb3 <= 0:
        return f"IQM walkers / SB3: n/a, signs differ ({difference})"
    line = f"IQM walkers / SB3: {walkers / sb3:.2f} ({difference})"
    if walkers < 0:
        return line + "; returns are negative: below 1 means walkers scored higher"
    return line


def own_evaluation_check(runs: list[Result]) -> str:
    """walkers' final/return_mean (its trainer's evaluation) vs the re-evaluation here."""
    gap = max(abs(r.own_final - r.returns.mean()) for r in runs)
    verdict = "the same" if gap < 1e-3 else "DIFFERENT"
    return f"walkers runs' own final/return_mean vs re-evaluation: {verdict} (max gap {gap:.3g})"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--env",
        action="append",
        help="walkers env config (conf/env: walker2d, pendulum, hopper, ...) or any gymnasium id "
        "with a Box action space; repeat for several envs (default: Walker2d-v5)",
    )
    parser.add_argument(
        "--steps", type=int, default=100_000, help="env steps per run (default: %(default)s)"
    )
    parser.add_argument(
        "--warmup",
        type=int,
        help="uniform random warm-up steps, no updates (default: a tenth of --steps)",
    )
    parser.add_argument(
        "--seeds", type=int, default=5, help="seeds 0..N-1, per library (default: %(default)s)"
    )
    parser.add_argument(
        "--episodes",
        type=int,
        default=10,
        help="final evaluation episodes per seed (default: %(default)s)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=torch.get_num_threads(),
        help="torch threads, the same for both libraries (default: %(default)s)",
    )
    args = parser.parse_args()
    args.env = args.env or ["Walker2d-v5"]
    for name in args.env:  # every env checked before the first (long) training
        try:
            env_overrides(name)
        except ValueError as e:
            parser.error(str(e))
    if args.warmup is None:
        args.warmup = args.steps // 10
    if min(args.steps, args.seeds, args.episodes, args.threads) < 1:
        parser.error("--steps, --seeds, --episodes and --threads must be at least 1")
    if not 0 <= args.warmup < args.steps:
        parser.error(f"--warmup {args.warmup} must be in [0, --steps)")
    return args


def main() -> None:
    args = parse_args()
    try:
        import sb3_td3  # noqa: F401  (stable-baselines3 itself)
    except ImportError:
        raise SystemExit(
            "error: stable-baselines3 is not installed: pip install -e '.[bench]'"
        ) from None
    torch.set_num_threads(args.threads)  # the evaluations here
    logging.getLogger("walkers").setLevel(logging.ERROR)  # e.g. "resumed without the buffer"
    os.environ.pop("MLFLOW_TRACKING_URI", None)  # every store is the temporary one
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_learning_") as tmp:
        for name in args.env:
            setup = make_setup(name, args, Path(tmp))
            results = compare(setup, list(range(args.seeds)))
            print_table(setup, args.warmup, results)
    print(f"\ntotal wall time: {(time.perf_counter() - start) / 60:.1f} min")


if __name__ == "__main__":
    main()
