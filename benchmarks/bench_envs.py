"""How N training envs step: a sequential loop, Gymnasium's SyncVectorEnv and AsyncVectorEnv, and
envpool, side by side on this machine's cores.

    make bench-envs          # or: .venv/bin/python benchmarks/bench_envs.py --envs 1,2,4,8

Walker2d-v5 as walkers builds it for training (``make_env``: the time limit and
``RecordEpisodeStatistics``), stepped with uniform random actions drawn up front, so the table is
the envs' cost alone: env steps/s summed over the N envs, and the ratio to one env stepped alone.
Each round steps every contender ``--steps`` env steps, in turn, so machine noise hits all alike.
The vector envs reset finished episodes in the same step (``autoreset_mode=SAME_STEP``: what
walkers' vectorized loop uses). envpool is not a walkers dependency: its rows appear when it
imports (``pip install envpool``; 1.2.5 registers the v5 MuJoCo ids), with ``num_threads`` = the
cores. A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np
from rounds import alternate, print_table

from walkers.training.envs import make_env

ENV = {"id": "Walker2d-v5", "max_episode_steps": 1000}


class Contender:
    """N envs behind one ``step(actions)``; ``run(steps)`` times ``steps`` env steps in all."""

    def __init__(self, n: int, step, close, action_space):
        self.n, self._step, self._close = n, step, close
        rng = np.random.default_rng(0)
        self.actions = rng.uniform(
            action_space.low, action_space.high, (64, n, *action_space.shape)
        ).astype(np.float32)

    def run(self, steps: int) -> float:
        calls = max(1, steps // self.n)
        start = time.perf_counter()
        for i in range(calls):
            self._step(self.actions[i % 64])
        return calls * self.n / (time.perf_counter() - start)


def sequential(n: int) -> Contender:
    envs = [make_env(ENV) for _ in range(n)]
    for i, env in enumerate(envs):
        env.reset(seed=i)

    def step(actions):
        for env, action in zip(envs, actions, strict=True):
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                env.reset()

    return Contender(n, step, lambda: [e.close() for e in envs], envs[0].action_space)


def vector(n: int, kind: str) -> Contender:
    fns = [lambda: make_env(ENV)] * n
    same_step = gym.vector.AutoresetMode.SAME_STEP
    if kind == "sync":
        envs = gym.vector.SyncVectorEnv(fns, autoreset_mode=same_step)
    else:
        envs = gym.vector.AsyncVectorEnv(fns, autoreset_mode=same_step, shared_memory=True)
    envs.reset(seed=0)
    return Contender(n, envs.step, envs.close, envs.single_action_space)


def envpool_contender(n: int) -> Contender | None:
    try:
        import envpool
    except ImportError:
        return None
    envs = envpool.make_gymnasium(
        ENV["id"], num_envs=n, seed=0, num_threads=min(n, os.cpu_count() or 1)
    )
    envs.reset()
    return Contender(n, envs.step, envs.close, envs.action_space)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", default="1,2,4,8", help="numbers of envs, e.g. 1,2,4,8")
    parser.add_argument("--steps", type=int, default=4000, help="env steps a round")
    parser.add_argument("--reps", type=int, default=3, help="alternating rounds")
    args = parser.parse_args()
    contenders = {"1 env alone": sequential(1)}
    for n in (int(x) for x in args.envs.split(",")):
        contenders[f"{n} envs, sequential loop"] = sequential(n)
        contenders[f"{n} envs, SyncVectorEnv"] = vector(n, "sync")
        contenders[f"{n} envs, AsyncVectorEnv"] = vector(n, "async")
        if (pool := envpool_contender(n)) is not None:
            contenders[f"{n} envs, envpool"] = pool
    for contender in contenders.values():
        contender.run(200)  # warm
    results = alternate(contenders, lambda c: c.run(args.steps), args.reps)
    print(
        f"\n{ENV['id']}, random actions, {os.cpu_count()} cores, "
        f"{args.reps} rounds x {args.steps} env steps"
    )
    print_table(results, "env steps/s", "1 env alone")
    for contender in contenders.values():
        contender._close()


if __name__ == "__main__":
    main()
