"""TD3 update step: walkers vs a plain eager PyTorch TD3 update, interleaved in one process.

    make bench            # or: .venv/bin/python benchmarks/bench_update.py --reps 8 [--device cuda]
                          #     [--phases: walkers' update by phase, host and device time]

Walker2d shapes (17-d observations, 6 actions), 256-256 networks, batch 256, fused Adam in all;
walkers eager and with ``compile=True`` (its loss computations through torch.compile; CUDA
graphs on a GPU), and on a GPU with ``capture=True`` (the whole update as CUDA graphs); where
bfloat16 is native (a GPU, a CPU with AMX or AVX-512 BF16) eager and compiled again with
``precision=bf16``. The plain reference is the textbook layout: two separate critic modules,
nn.Linear layers. Rounds alternate so machine noise hits all alike; the table reports medians
and the ratio (below 1: walkers is faster). On the CPU a second table breaks the eager update
down by kind of work. A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import numpy as np
import torch
from rounds import alternate, print_table
from torch import nn
from torch.nn import functional as F

from walkers.agents.base import Transition, cpu_has_native_bf16
from walkers.agents.factory import defaults_for
from walkers.agents.td3 import TD3

OBS, ACT, BATCH, CAPACITY = 17, 6, 256, 100_000


class PlainTD3Update:
    """The reference: separate critics, separate optimizer steps, one op per line."""

    def __init__(self, device: torch.device):
        def mlp(i, o):
            return nn.Sequential(
                nn.Linear(i, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, o)
            )

        self.actor, self.q1, self.q2 = (
            mlp(OBS, ACT).to(device),
            mlp(OBS + ACT, 1).to(device),
            mlp(OBS + ACT, 1).to(device),
        )
        self.actor_t, self.q1_t, self.q2_t = (
            copy.deepcopy(m) for m in (self.actor, self.q1, self.q2)
        )
        critic_params = [*self.q1.parameters(), *self.q2.parameters()]
        self.q_opt = torch.optim.Adam(critic_params, lr=3e-4, fused=True)
        self.a_opt = torch.optim.Adam(self.actor.parameters(), lr=3e-4, fused=True)
        self.data = [
            torch.randn(CAPACITY, OBS, device=device),
            torch.rand(CAPACITY, ACT, device=device) * 2 - 1,
            torch.randn(CAPACITY, device=device),
            torch.randn(CAPACITY, OBS, device=device),
            torch.zeros(CAPACITY, device=device),
        ]
        self.device = device
        self.n = 0

    def __call__(self):
        idx = torch.randint(0, CAPACITY, (BATCH,), device=self.device)
        obs, act, rew, next_obs, term = (d[idx] for d in self.data)
        with torch.no_grad():
            noise = (torch.randn_like(act) * 0.2).clamp(-0.5, 0.5)
            next_act = (torch.tanh(self.actor_t(next_obs)) + noise).clamp(-1, 1)
            x = torch.cat([next_obs, next_act], 1)
            y = rew + 0.99 * (1 - term) * torch.min(self.q1_t(x), self.q2_t(x)).view(-1)
        x = torch.cat([obs, act], 1)
        loss = F.mse_loss(self.q1(x).view(-1), y) + F.mse_loss(self.q2(x).view(-1), y)
        self.q_opt.zero_grad()
        loss.backward()
        self.q_opt.step()
        self.n += 1
        if self.n % 2 == 0:
            actor_loss = -self.q1(torch.cat([obs, torch.tanh(self.actor(obs))], 1)).mean()
            self.a_opt.zero_grad()
            actor_loss.backward()
            self.a_opt.step()
            with torch.no_grad():
                for net, target in (
                    (self.actor, self.actor_t),
                    (self.q1, self.q1_t),
                    (self.q2, self.q2_t),
                ):
                    for p, tp in zip(net.parameters(), target.parameters(), strict=True):
                        tp.mul_(0.995).add_(p, alpha=0.005)


def walkers_agent(
    device: torch.device, compile: bool = False, capture: bool = False, precision: str = "fp32"
) -> TD3:
    agent = TD3(
        OBS,
        [-1.0] * ACT,
        [1.0] * ACT,
        device=str(device),
        **defaults_for(
            TD3,
            learning_starts=0,
            buffer_size=CAPACITY,
            compile=compile,
            capture=capture,
            precision=precision,
        ),
    )
    rng = np.random.default_rng(0)
    for _ in range(CAPACITY // 10):
        o = rng.normal(size=OBS).astype(np.float32)
        a = rng.uniform(-1, 1, ACT).astype(np.float32)
        agent.observe(Transition(o, a, 1.0, o, False, False))
    for _ in range(8):  # compiled or captured here, not inside the timed rounds
        agent.update()
    return agent


def walkers_update(
    device: torch.device, compile: bool = False, capture: bool = False, precision: str = "fp32"
):
    return walkers_agent(device, compile, capture, precision).update


#: The phases of walkers' TD3 update, by the name the update calls them under (td3.py).
PHASES = ("sample", "critic_loss", "actor_loss", "skip_nonfinite", "soft_update", "record_health")


def phase_profile(device: torch.device, n: int = 50) -> dict[str, tuple[float, float, int]]:
    """Walkers' eager TD3 update by phase: per update, (host ms, device ms, ops dispatched) of
    each phase (sampling K buffers, the losses, the guard, the target updates, the counters),
    the optimizer steps and the backward passes as the rest. Each phase is wrapped in a
    ``record_function`` range; a range's host time is the Python and dispatch it costs, its
    device time (CUDA) the kernels it launched."""
    from torch.profiler import ProfilerActivity, profile, record_function

    import walkers.agents.td3 as td3_module

    agent = walkers_agent(device)

    def ranged(name, fn):
        def wrapped(*args, **kwargs):
            with record_function(f"phase::{name}"):
                return fn(*args, **kwargs)

        return wrapped

    originals = {name: getattr(td3_module, name) for name in ("skip_nonfinite", "soft_update")}
    for name in ("sample", "critic_loss", "actor_loss", "record_health"):
        setattr(agent, name, ranged(name, getattr(agent, name)))
    for name, fn in originals.items():
        setattr(td3_module, name, ranged(name, fn))
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    try:
        with profile(activities=activities) as prof:
            with record_function("phase::whole update"):
                for _ in range(n):
                    agent.update()
                synchronize(device)
    finally:
        for name, fn in originals.items():
            setattr(td3_module, name, fn)
    phases = {}
    for event in prof.key_averages():
        # on CUDA a range comes twice under one key: its host event (host time, no device time)
        # and its device-side annotation (the other way round); keep each one's own time
        if event.key.startswith("phase::"):
            name = event.key[len("phase::") :]
            host, device_ms = phases.get(name, (0.0, 0.0))
            phases[name] = (
                max(host, event.cpu_time_total / 1e3 / n),
                max(device_ms, getattr(event, "device_time_total", 0.0) / 1e3 / n),
            )
    ops = sum(e.count for e in prof.key_averages() if e.key.startswith("aten::")) / n
    return {name: (*phases.get(name, (0.0, 0.0)), 0) for name in (*PHASES, "whole update")} | {
        "aten ops dispatched per update": (ops, 0.0, 0)
    }


def time_ms(fn, n: int, device: torch.device) -> float:
    for _ in range(10):
        fn()
    synchronize(device)
    start = time.perf_counter()
    for _ in range(n):
        fn()
    synchronize(device)
    return (time.perf_counter() - start) / n * 1e3


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


# Where an eager update's time goes: aten ops by kind; the rest (Python, autograd engine,
# dispatch, the optimizer's Python wrapper) is what the profiler sees outside any aten op.
MATMUL_OPS = {"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm"}
OPTIMIZER_OPS = {
    "aten::_fused_adam_", "aten::_foreach_lerp_", "aten::lerp_", "aten::_foreach_add_",
    "aten::_foreach_sub_",
}  # fmt: skip
ELEMENTWISE_OPS = {
    "aten::clamp_min", "aten::threshold_backward", "aten::mul", "aten::add", "aten::add_",
    "aten::sub", "aten::pow", "aten::tanh", "aten::tanh_backward", "aten::clamp", "aten::min",
    "aten::sum", "aten::mean", "aten::fill_", "aten::isfinite", "aten::rsub", "aten::neg",
    "aten::masked_fill_", "aten::randn", "aten::normal_", "aten::abs", "aten::eq", "aten::ne",
    "aten::logical_and", "aten::bitwise_and_", "aten::bitwise_not", "aten::div",
}  # fmt: skip
SAMPLING_OPS = {"aten::index", "aten::randint", "aten::random_"}
OP_KINDS = {
    "matmuls": MATMUL_OPS,
    "Adam, target updates": OPTIMIZER_OPS,
    "elementwise": ELEMENTWISE_OPS,
    "batch sampling": SAMPLING_OPS,
}
OTHER_OPS = "copies, views, allocations, other"


def breakdown(update, n: int = 100) -> dict[str, float]:
    """ms per update in each kind of work (torch.profiler, self time of each op)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        for _ in range(n):
            update()
        wall = (time.perf_counter() - start) / n * 1e3
    kinds = dict.fromkeys([*OP_KINDS, OTHER_OPS], 0.0)
    for event in prof.key_averages():
        if event.key.startswith("aten::"):
            kind = next((k for k, ops in OP_KINDS.items() if event.key in ops), OTHER_OPS)
            kinds[kind] += event.self_cpu_time_total / 1e3 / n
    # What no op accounts for; the profiler's own cost lands here too.
    kinds["Python, autograd, dispatch, profiler"] = wall - sum(kinds.values())
    return kinds | {"update (profiled)": wall}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=6, help="alternating rounds")
    parser.add_argument("--updates", type=int, default=100, help="updates per round")
    parser.add_argument("--device", default="cpu", help="cpu | cuda")
    parser.add_argument(
        "--phases", action="store_true", help="also walkers' update by phase (host and device ms)"
    )
    args = parser.parse_args()
    device = torch.device(args.device)
    torch.manual_seed(0)
    contenders = {
        "plain eager TD3": PlainTD3Update(device),
        "walkers TD3": walkers_update(device),
        "walkers TD3 compile": walkers_update(device, compile=True),
    }
    if device.type == "cuda":  # the whole update as CUDA graphs (algo.capture=true)
        contenders["walkers TD3 capture"] = walkers_update(device, capture=True)
    if device.type == "cuda" or cpu_has_native_bf16():  # algo.precision=bf16: an arm of its own
        contenders["walkers TD3 bf16"] = walkers_update(device, precision="bf16")
        contenders["walkers TD3 compile bf16"] = walkers_update(device, True, precision="bf16")
    times = alternate(contenders, lambda fn: time_ms(fn, args.updates, device), args.reps)
    where = f"{torch.get_num_threads()} threads" if device.type == "cpu" else str(device)
    print(
        f"TD3 update, Walker2d shapes, batch {BATCH}, {where}, "
        f"{args.reps} rounds x {args.updates} updates"
    )
    print_table(times, "median ms", baseline="plain eager TD3")
    if device.type == "cpu":
        print("\nWhere the walkers TD3 update's time goes (eager, torch.profiler self times):")
        kinds = breakdown(contenders["walkers TD3"])
        total = kinds["update (profiled)"]
        print(f"| {'work':<36} | ms/update | share |")
        print(f"|{'-' * 38}|-----------|-------|")
        for kind, ms in kinds.items():
            print(f"| {kind:<36} | {ms:>9.2f} | {ms / total:>5.0%} |")
        unprofiled = statistics.median(times["walkers TD3"])
        print(f"(the same update unprofiled: {unprofiled:.2f} ms, the median above)")
    if args.phases:
        print(
            f"\nwalkers' eager TD3 update by phase on {device} (torch.profiler ranges, per update;"
        )
        print("the optimizer steps and backward passes are the whole less the phases):")
        print("| phase | host ms (Python + dispatch) | device ms (kernels) |")
        print("|---|---|---|")
        for phase, (host, on_device, _) in phase_profile(device).items():
            print(f"| {phase} | {host:.3f} | {on_device:.3f} |")


if __name__ == "__main__":
    main()
