"""TD3 update step: walkers vs a plain eager PyTorch TD3 update, interleaved in one process.

    make bench            # or: .venv/bin/python benchmarks/bench_update.py --reps 8

Walker2d shapes (17-d observations, 6 actions), 256-256 networks, batch 256, fused Adam in
both. The plain reference is the textbook layout: two separate critic modules, nn.Linear layers.
Rounds alternate between the two so machine noise hits both alike; the table reports medians and
the ratio (below 1: walkers is faster). A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np
import torch
from rounds import alternate, print_table
from torch import nn
from torch.nn import functional as F

from walkers.agents.base import Transition
from walkers.agents.td3 import TD3

OBS, ACT, BATCH, CAPACITY = 17, 6, 256, 100_000


class PlainTD3Update:
    """The reference: separate critics, separate optimizer steps, one op per line."""

    def __init__(self):
        def mlp(i, o):
            return nn.Sequential(
                nn.Linear(i, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, o)
            )

        self.actor, self.q1, self.q2 = mlp(OBS, ACT), mlp(OBS + ACT, 1), mlp(OBS + ACT, 1)
        self.actor_t, self.q1_t, self.q2_t = (
            copy.deepcopy(m) for m in (self.actor, self.q1, self.q2)
        )
        critic_params = [*self.q1.parameters(), *self.q2.parameters()]
        self.q_opt = torch.optim.Adam(critic_params, lr=3e-4, fused=True)
        self.a_opt = torch.optim.Adam(self.actor.parameters(), lr=3e-4, fused=True)
        self.data = [
            torch.randn(CAPACITY, OBS),
            torch.rand(CAPACITY, ACT) * 2 - 1,
            torch.randn(CAPACITY),
            torch.randn(CAPACITY, OBS),
            torch.zeros(CAPACITY),
        ]
        self.n = 0

    def __call__(self):
        idx = torch.randint(0, CAPACITY, (BATCH,))
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


def walkers_update():
    agent = TD3(OBS, [-1.0] * ACT, [1.0] * ACT, learning_starts=0, buffer_size=CAPACITY)
    rng = np.random.default_rng(0)
    for _ in range(CAPACITY // 10):
        o = rng.normal(size=OBS).astype(np.float32)
        a = rng.uniform(-1, 1, ACT).astype(np.float32)
        agent.observe(Transition(o, a, 1.0, o, False, False))
    return agent.update


def time_ms(fn, n: int) -> float:
    for _ in range(10):
        fn()
    start = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - start) / n * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=6, help="alternating rounds")
    parser.add_argument("--updates", type=int, default=100, help="updates per round")
    args = parser.parse_args()
    torch.manual_seed(0)
    contenders = {"plain eager TD3": PlainTD3Update(), "walkers TD3": walkers_update()}
    times = alternate(contenders, lambda fn: time_ms(fn, args.updates), args.reps)
    print(
        f"TD3 update, Walker2d shapes, batch {BATCH}, {torch.get_num_threads()} threads, "
        f"{args.reps} rounds x {args.updates} updates"
    )
    print_table(times, "median ms", baseline="plain eager TD3")


if __name__ == "__main__":
    main()
