"""Env steps per second in the learning phase: walkers vs Stable-Baselines3 and SBX, side by side.

    make bench-throughput          # the whole machine, then pinned to one core (taskset -c 0)
    .venv/bin/python benchmarks/bench_throughput.py --reps 4 [--only TD3,SAC]

Each library runs at its own defaults, as its users get it: walkers at one torch thread
(``torch_threads: 1``), Stable-Baselines3 at torch's default (every core), SBX (Stable-Baselines
in JAX) at JAX's. Pinned (``taskset -c 0``), all have one core; the per-core process rows are
left out there.

Walker2d-v5, reference hyperparameters for all (256-256, batch 256, one gradient step per env step,
lr 3e-4, gamma 0.99, tau 0.005; SAC with the learned temperature, target entropy -|A|, in both).
Each contender first runs past its warm-up untimed, then the contenders take turns, ``--steps`` env
steps a round, so machine noise hits all alike. The table gives the median env steps/s and the
ratio to SB3's TD3 (above 1: faster). Seeds trained together count in aggregate: ``K=`` rows are
one process with a population of K, ``procs x`` rows are one process per core with one
thread each, as a joblib multirun runs them.
PPO has its own table, against SB3's PPO: both at the reference settings (64-64 tanh, rollouts of
2048 steps, 10 epochs of 32 minibatches of 64, lr 3e-4, observation and reward normalization: in
the agent for walkers, ``VecNormalize`` for SB3, as RL-Zoo runs MuJoCo); a round there is one
rollout and its update. Its ``N envs`` rows are walkers' PPO with ``algo.num_envs=N``: the same
rollout of 2048 steps, 2048 / N from each of N envs acting as one batch.
Then: the TD3 update alone, an estimate of its FLOPs, this machine's fp32
matmul rate (one thread), and the memory of a full 1M-transition replay buffer. SB3 and SBX are
benchmark-only dependencies (``pip install -e '.[sb3]'``, ``'.[bench]'`` for SBX and its JAX:
never walkers' runtime); without them their rows are skipped. ``--only PPO``
runs only the contenders with PPO in their name. A benchmark, not a test: nothing here asserts on
time.

``--device cuda`` runs every contender on the GPU (walkers' replay, sampling and updates, SB3's
``device="cuda"``); the population rows then take ``--population`` (e.g. ``1,4,16``) for TD3 and
for CrossQ at the paper's width, the per-core process rows are left out, and so is the CPU-only
tail.
"""

from __future__ import annotations

import argparse
import importlib
import multiprocessing as mp
import os
import time
from functools import partial

import gymnasium as gym
import torch
from rounds import alternate, print_table

from walkers.agents.base import cpu_has_native_bf16
from walkers.agents.crossq import CrossQ
from walkers.agents.ddpg import DDPG
from walkers.agents.factory import defaults_for
from walkers.agents.ppo import PPO
from walkers.agents.reinforce import Reinforce
from walkers.agents.sac import SAC
from walkers.agents.td3 import TD3
from walkers.agents.td7 import TD7
from walkers.data.replay import DATA_FIELDS, ReplayBuffer
from walkers.training.envs import env_spaces, make_env, make_vector_env
from walkers.training.loops import Lockstep, online_step, vectorized_step

ENV_ID, HIDDEN, BATCH, WARMUP = "Walker2d-v5", 256, 256, 1_000
ENV_CFG = {"id": ENV_ID, "max_episode_steps": 1000}  # as conf/env/walker2d.yaml builds it
PPO_ROLLOUT = 2048  # PPO's reference rollout: a PPO round is one rollout and its update
PPO_ENVS = (4, 8)  # the walkers PPO rows with algo.num_envs envs acting as one batch
PPO_ROWS = ("walkers PPO", *(f"walkers PPO {n} envs" for n in PPO_ENVS), "SB3 PPO")
#: CrossQ's critic widths on a CPU: the paper's 2048, sb3-contrib's 1024, and narrower ones
CROSSQ_WIDTHS = (2048, 1024, 512, 256)
CROSSQ_ROUND = 100  # env steps per round of the CrossQ rows (a 2048-wide update takes ~0.1 s)
DEVICE = "cpu"  # where every contender runs: set once by --device, before any is built


#: torch's own thread default here (every core it may use): Stable-Baselines3's, and SBX's
#: torch side; set before each contender's round, as each library runs at its own default
TORCH_DEFAULT_THREADS = torch.get_num_threads()


class WalkersLoop:
    """The trainer's single-run step (:func:`walkers.training.loops.online_step`: act, step,
    observe, update) around one walkers agent, without the run's books."""

    torch_threads = 1  # walkers.train's default (torch_threads: 1)

    def __init__(self, agent_cls, **kwargs):
        self.env = make_env(ENV_CFG)
        spaces = env_spaces(self.env)
        self.agent = agent_cls(**spaces, seed=0, device=DEVICE, **defaults_for(agent_cls, **kwargs))
        self.obs, _ = self.env.reset(seed=0)
        self.losses: dict = {}

    def run(self, steps: int) -> None:
        for _ in range(steps):
            self.obs, _ = online_step(self.agent, self.env, self.obs, self.losses)


class PopulationLoop:
    """The trainer's population step (``population=K``: :class:`walkers.training.loops.Lockstep`,
    K envs as one vector env, one batched update for all members), without the runs' books."""

    torch_threads = 1

    def __init__(self, k: int, agent_cls=TD3, **kwargs):
        envs = make_vector_env(ENV_CFG, k, step_info=False)
        spaces = env_spaces(envs.envs[0])
        self.agent = agent_cls(
            **spaces, seed=0, population=k, device=DEVICE, **defaults_for(agent_cls, **kwargs)
        )
        self.lockstep = Lockstep(self.agent, envs, envs.reset(seed=list(range(k)))[0])
        self.env_steps_per_step = k

    def run(self, steps: int) -> None:
        for _ in range(steps):
            self.lockstep.step()


class ParallelLoops:
    """``n`` processes with one torch thread each, each running its own loop (a TD3 seed, or a
    population of ``k``): what a multirun with ``hydra/launcher=joblib`` does with the cores."""

    torch_threads = 1  # the driver's own: its workers set theirs

    def __init__(self, n: int, k: int = 1, **kwargs):
        ctx = mp.get_context("spawn")
        self.pipes = []
        for _ in range(n):
            parent, child = ctx.Pipe()
            ctx.Process(target=_loop_worker, args=(child, k, kwargs), daemon=True).start()
            self.pipes.append(parent)
        self.env_steps_per_step = n * k

    def run(self, steps: int) -> None:
        for pipe in self.pipes:
            pipe.send(steps)
        for pipe in self.pipes:
            pipe.recv()


def _loop_worker(pipe, k: int, kwargs: dict) -> None:
    torch.set_num_threads(1)
    loop = WalkersLoop(TD3, **kwargs) if k == 1 else PopulationLoop(k, **kwargs)
    try:
        while True:
            loop.run(pipe.recv())
            pipe.send("done")
    except EOFError:  # the benchmark is over
        pass


class SB3Loop:
    """Stable-Baselines3's own ``learn`` loop, continued in chunks (``library="sbx"``: SBX's,
    the same API on JAX)."""

    torch_threads = None  # SB3's default: torch's own (every core it may use)

    def __init__(self, algo_name: str, library: str = "stable_baselines3"):
        cls = getattr(importlib.import_module(library), algo_name)
        self.model = cls(
            "MlpPolicy",
            gym.make(ENV_ID),
            learning_rate=3e-4,
            buffer_size=1_000_000,
            learning_starts=WARMUP,
            batch_size=BATCH,
            tau=0.005,
            gamma=0.99,
            train_freq=1,
            gradient_steps=1,
            policy_kwargs={"net_arch": [HIDDEN, HIDDEN]},
            seed=0,
            device=DEVICE,
        )
        _log_in_memory(self.model)

    def run(self, steps: int) -> None:
        self.model.learn(total_timesteps=steps, reset_num_timesteps=False)


def _log_in_memory(model) -> None:
    """SB3's logger in memory, as the twin's: left to itself, each ``learn`` makes a
    ``$TMPDIR/SB3-<time>`` folder, and nobody asked for those."""
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))


def walkers_crossq(width: int) -> WalkersLoop:
    """walkers' CrossQ at its defaults (the paper's) with critics ``width`` wide."""
    loop = WalkersLoop(
        CrossQ, critic_hidden_sizes=[width, width], batch_size=BATCH, learning_starts=WARMUP
    )
    loop.round_steps = CROSSQ_ROUND
    return loop


class SB3CrossQLoop(SB3Loop):
    """sb3-contrib's CrossQ at the same settings (its defaults but the critics' width;
    ``library="sbx"``: SBX's)."""

    round_steps = CROSSQ_ROUND

    def __init__(self, width: int, library: str = "sb3_contrib"):
        cls = importlib.import_module(library).CrossQ
        self.model = cls(
            "MlpPolicy",
            gym.make(ENV_ID),
            learning_starts=WARMUP,
            batch_size=BATCH,
            policy_kwargs={"net_arch": {"pi": [HIDDEN, HIDDEN], "qf": [width, width]}},
            seed=0,
            device=DEVICE,
        )
        _log_in_memory(self.model)


def walkers_ppo() -> WalkersLoop:
    """walkers' PPO at its defaults (conf/algo/ppo.yaml: the reference settings)."""
    loop = WalkersLoop(PPO)
    loop.round_steps = PPO_ROLLOUT
    return loop


class VectorPPOLoop:
    """walkers' PPO with ``num_envs`` envs acting as one batch (the trainer's
    :func:`walkers.training.loops.vectorized_step`: one vector env in this process, episodes
    reset in the step)."""

    round_steps = PPO_ROLLOUT
    torch_threads = 1

    def __init__(self, num_envs: int):
        self.envs = make_vector_env(ENV_CFG, num_envs)
        spaces = env_spaces(self.envs.envs[0])
        hp = defaults_for(PPO, num_envs=num_envs, total_steps=1_000_000)
        self.agent = PPO(**spaces, seed=0, device=DEVICE, **hp)
        self.obs, _ = self.envs.reset(seed=0)
        self.losses: dict = {}

    def run(self, steps: int) -> None:
        for _ in range(steps // self.envs.num_envs):
            self.obs = vectorized_step(self.agent, self.envs, self.obs, self.losses).next_obs


class SB3PPOLoop:
    """Stable-Baselines3's PPO at the same settings (its defaults, value clipping off as walkers'
    default), on ``VecNormalize``; ``learn`` collects whole rollouts, so a round is one."""

    round_steps = PPO_ROLLOUT

    def __init__(self):
        from stable_baselines3 import PPO as SB3PPO
        from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

        env = VecNormalize(DummyVecEnv([lambda: gym.make(ENV_ID)]), gamma=0.99)
        self.model = SB3PPO(
            "MlpPolicy",
            env,
            learning_rate=3e-4,
            n_steps=PPO_ROLLOUT,
            batch_size=64,
            n_epochs=10,
            gamma=0.99,
            gae_lambda=0.95,
            clip_range=0.2,
            clip_range_vf=None,
            max_grad_norm=0.5,
            policy_kwargs={"net_arch": [64, 64], "activation_fn": torch.nn.Tanh},
            seed=0,
            device=DEVICE,
        )
        _log_in_memory(self.model)

    def run(self, steps: int) -> None:
        self.model.learn(total_timesteps=steps, reset_num_timesteps=False)


def crossq_population(k: int) -> PopulationLoop:
    """K CrossQ seeds at the paper's width trained together (a GPU's case)."""
    loop = PopulationLoop(
        k, CrossQ, critic_hidden_sizes=[2048, 2048], batch_size=BATCH, learning_starts=WARMUP
    )
    loop.round_steps = CROSSQ_ROUND
    return loop


def contenders(only: str | None = None, population: tuple[int, ...] = (2, 4)) -> dict:
    # the eager rows are eager on a GPU too (capture=auto would capture them there)
    common = {"lr": 3e-4, "batch_size": BATCH, "learning_starts": WARMUP, "capture": False}
    loops = {
        "walkers TD3": lambda: WalkersLoop(TD3, hidden_sizes=[HIDDEN, HIDDEN], **common),
        "walkers TD3 compile": lambda: WalkersLoop(
            TD3, hidden_sizes=[HIDDEN, HIDDEN], compile=True, **common
        ),
        "walkers DDPG": lambda: WalkersLoop(DDPG, hidden_sizes=[HIDDEN, HIDDEN], **common),
        "walkers SAC": lambda: WalkersLoop(SAC, hidden_sizes=[HIDDEN, HIDDEN], **common),
        "walkers SAC compile": lambda: WalkersLoop(
            SAC, hidden_sizes=[HIDDEN, HIDDEN], compile=True, **common
        ),
        "walkers TD7": lambda: WalkersLoop(TD7, hidden_sizes=[HIDDEN, HIDDEN], **common),
        **{f"walkers CrossQ {width}": partial(walkers_crossq, width) for width in CROSSQ_WIDTHS},
        "walkers REINFORCE": lambda: WalkersLoop(Reinforce, hidden_sizes=[HIDDEN, HIDDEN]),
        "walkers PPO": walkers_ppo,
        **{f"walkers PPO {n} envs": partial(VectorPPOLoop, n) for n in PPO_ENVS},
        # population=K: the aggregate env steps/s of K seeds trained together
        **{
            f"walkers TD3 K={k}": partial(
                PopulationLoop, k, hidden_sizes=[HIDDEN, HIDDEN], **common
            )
            for k in population
            if k > 1
        },
    }
    if DEVICE == "cuda" or cpu_has_native_bf16():  # algo.precision=bf16: an arm of its own
        loops |= {
            f"walkers {name} compile bf16": partial(
                WalkersLoop, cls, hidden_sizes=[HIDDEN, HIDDEN], compile=True, precision="bf16",
                **common,
            )
            for name, cls in (("TD3", TD3), ("SAC", SAC))
        }  # fmt: skip
    if DEVICE == "cpu":
        if len(os.sched_getaffinity(0)) > 1:  # the cores as processes, a seed (or K=2) each
            loops |= {
                "2 procs x TD3": lambda: ParallelLoops(2, hidden_sizes=[HIDDEN, HIDDEN], **common),
                "2 procs x TD3 K=2": lambda: ParallelLoops(
                    2, k=2, hidden_sizes=[HIDDEN, HIDDEN], **common
                ),
                "2 procs x TD3 compile": lambda: ParallelLoops(
                    2, hidden_sizes=[HIDDEN, HIDDEN], compile=True, **common
                ),
            }
    else:  # on a GPU the paper's CrossQ width, K seeds at a time; whole updates captured
        loops |= {f"walkers CrossQ 2048 K={k}": partial(crossq_population, k) for k in population}
        captured = {**common, "capture": True, "hidden_sizes": [HIDDEN, HIDDEN]}
        loops |= {
            "walkers TD3 capture": lambda: WalkersLoop(TD3, **captured),
            "walkers SAC capture": lambda: WalkersLoop(SAC, **captured),
            "walkers TD7 capture": lambda: WalkersLoop(TD7, **captured),
            **{
                f"walkers TD3 capture K={k}": partial(PopulationLoop, k, **captured)
                for k in population
                if k > 1
            },
        }
    try:
        import stable_baselines3  # noqa: F401

        loops |= {
            "SB3 TD3": lambda: SB3Loop("TD3"),
            "SB3 DDPG": lambda: SB3Loop("DDPG"),
            "SB3 SAC": lambda: SB3Loop("SAC"),  # ent_coef="auto": the learned temperature
            "sb3-contrib CrossQ 2048": partial(SB3CrossQLoop, 2048),
            "sb3-contrib CrossQ 256": partial(SB3CrossQLoop, 256),
        }
        loops["SB3 PPO"] = SB3PPOLoop
    except ImportError:
        print("stable-baselines3 not installed: SB3 rows skipped (pip install -e '.[sb3]')")
    try:
        import sbx  # noqa: F401

        loops |= {
            "SBX TD3": partial(SB3Loop, "TD3", "sbx"),
            "SBX SAC": partial(SB3Loop, "SAC", "sbx"),
            "SBX CrossQ 2048": partial(SB3CrossQLoop, 2048, "sbx"),
            "SBX CrossQ 256": partial(SB3CrossQLoop, 256, "sbx"),
        }
    except ImportError:
        print("sbx-rl not installed: SBX rows skipped (pip install -e '.[bench]')")
    wanted = None if only is None else only.split(",")
    return {
        name: make()
        for name, make in loops.items()
        if wanted is None or any(part in name for part in wanted)
    }


def matmul_gflops(n: int = 256, reps: int = 200) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    for _ in range(10):
        a @ b
    start = time.perf_counter()
    for _ in range(reps):
        a @ b
    return 2 * n**3 * reps / (time.perf_counter() - start) / 1e9


def td3_update_gflop(obs: int, act: int, hidden: int = HIDDEN, batch: int = BATCH) -> float:
    """Matmul FLOPs of one TD3 update (policy delay 2 averaged), backward = 2x forward."""

    def mlp(i, o):  # forward FLOPs of an i -> hidden -> hidden -> o MLP on a batch
        return 2 * batch * (i * hidden + hidden * hidden + hidden * o)

    actor, critic = mlp(obs, act), mlp(obs + act, 1)
    target = actor + 2 * critic  # target actor + two target critics, forward only
    critics = 2 * critic * 3  # two critics, forward + backward
    actor_step = (actor + critic) * 3 / 2  # every 2nd update: actor through critic 1
    return (target + critics + actor_step) / 1e9


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=4, help="alternating rounds")
    parser.add_argument("--steps", type=int, default=1_000, help="env steps per round")
    parser.add_argument(
        "--only", help="the contenders whose name contains one of these (e.g. PPO, or CrossQ,SAC)"
    )
    parser.add_argument("--device", default="cpu", help="cpu | cuda: where every contender runs")
    parser.add_argument(
        "--population", default="2,4", help="population sizes of the K= rows (e.g. 1,4,16)"
    )
    args = parser.parse_args()
    global DEVICE
    DEVICE = args.device
    loops = contenders(args.only, tuple(int(k) for k in args.population.split(",")))
    for loop in loops.values():
        loop.run(WARMUP + 100)  # past the warm-up (and any compile): every timed step learns

    def steps_per_second(loop) -> float:  # env steps: a population steps K envs per loop step
        torch.set_num_threads(loop.torch_threads or TORCH_DEFAULT_THREADS)
        steps = getattr(loop, "round_steps", args.steps)
        start = time.perf_counter()
        loop.run(steps)
        return steps * getattr(loop, "env_steps_per_step", 1) / (time.perf_counter() - start)

    sps = alternate(loops, steps_per_second, args.reps)
    cores = sorted(os.sched_getaffinity(0))
    where = (
        f"on {DEVICE}"
        if DEVICE != "cpu"
        else f"pinned to core {cores[0]}"
        if len(cores) == 1
        else f"{len(cores)} cores, each library at its default threads (walkers 1, torch "
        f"{TORCH_DEFAULT_THREADS}, JAX its own)"
    )
    on_policy = {name: sps.pop(name) for name in PPO_ROWS if name in sps}
    crossq = {name: sps.pop(name) for name in list(sps) if "CrossQ" in name}
    if crossq:
        crossq |= {name: sps[name] for name in ("walkers SAC", "SB3 SAC") if name in sps}
        print(
            f"\n{ENV_ID}, CrossQ by critic width (actor {HIDDEN}-{HIDDEN}, batch {BATCH}) beside "
            f"SAC, {where}, {args.reps} rounds x {CROSSQ_ROUND} steps"
        )
        print_table(crossq, "env steps/s", baseline="walkers SAC")
    if set(sps) - set(crossq):  # not only the SAC rows the CrossQ table already shows
        print(
            f"\n{ENV_ID}, learning phase, {HIDDEN}-{HIDDEN}, batch {BATCH}, 1 gradient step per "
            f"env step, {where}, {args.reps} rounds x {args.steps} steps"
        )
        print_table(sps, "env steps/s", baseline="SB3 TD3")
    if on_policy:
        print(
            f"\n{ENV_ID}, PPO at the reference settings, {where}, "
            f"{args.reps} rounds x 1 rollout of {PPO_ROLLOUT} steps and its update"
        )
        print_table(on_policy, "env steps/s", baseline="SB3 PPO")
    if "walkers TD3" not in loops or DEVICE != "cpu":
        return

    td3 = loops["walkers TD3"].agent
    spaces = env_spaces(loops["walkers TD3"].env)
    obs_dim, act_dim = spaces["obs_dim"], len(spaces["action_low"])
    torch.set_num_threads(1)
    for _ in range(10):
        td3.update()
    start = time.perf_counter()
    for _ in range(200):
        td3.update()
    update_ms = (time.perf_counter() - start) / 200 * 1e3
    gflop, rate = td3_update_gflop(obs_dim, act_dim), matmul_gflops()
    print(f"\nTD3 update alone: {update_ms:.2f} ms; its matmuls: {gflop * 1e3:.1f} MFLOP, i.e.")
    print(
        f"{gflop / rate * 1e3:.2f} ms at this machine's {rate:.0f} GFLOP/s (fp32 256x256x256): "
        f"{gflop / rate * 1e3 / update_ms:.0%} of the update is matmul at peak rate."
    )
    buffer = ReplayBuffer(1_000_000, obs_dim, act_dim, torch.device("cpu"))
    nbytes = sum(
        getattr(buffer, name).numel() * getattr(buffer, name).element_size() for name in DATA_FIELDS
    )
    print(f"Replay buffer, 1M {ENV_ID} transitions, float32: {nbytes / 1e6:.0f} MB preallocated.")


if __name__ == "__main__":
    main()
