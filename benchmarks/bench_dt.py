"""The Decision Transformer's gradient step at its reference size, on Walker2d shapes.

    .venv/bin/python benchmarks/bench_dt.py [--devices cpu,cuda] [--reps 5] [--steps 20]

The agent at its declared defaults (``conf/algo/dt.yaml``: context 20, embedding 128, 3 blocks,
1 head, batch 64, dropout 0.1, AdamW), sampling from a synthetic dataset of Walker2d-v5 shapes
(17-d observations, 6-d actions, 20 episodes of 1,000 steps): what ``algo=dt env=walker2d``
runs per gradient step, the sampling of the batch included; beside it on each device the same
agent with ``algo.precision=bf16`` (bfloat16 autocast) and one with torch's encoder for its blocks;
with ``--compile`` also one whose model runs through ``torch.compile`` (a minute to compile, so
off by default: the GPU session's part has 25 s).
The contenders take turns, ``--steps`` gradient steps a round, and the table gives the median ms
per step and the ratio to the first. A benchmark, not a test: nothing here asserts on time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from rounds import alternate, print_table
from torch import nn

from walkers.agents.dt import DecisionTransformer
from walkers.agents.factory import defaults_for
from walkers.data.datasets import OfflineData
from walkers.data.episodes import Episode

OBS, ACT, EPISODES, STEPS = 17, 6, 20, 1_000


def walker2d_shaped_data(seed: int = 0) -> OfflineData:
    rng = np.random.default_rng(seed)
    episodes = [
        Episode(
            rng.normal(size=(STEPS + 1, OBS)).astype(np.float32),
            rng.uniform(-1, 1, size=(STEPS, ACT)).astype(np.float32),
            rng.normal(1.0, 0.5, size=STEPS).astype(np.float32),
            np.zeros(STEPS, bool),
            np.arange(STEPS) == STEPS - 1,
        )
        for _ in range(EPISODES)
    ]
    return OfflineData("synthetic", "Walker2d-v5", episodes, None, None)


class TorchEncoderBlocks(nn.Module):
    """torch's ``nn.TransformerEncoder`` in place of walkers' blocks and final LayerNorm."""

    def __init__(self, embed_dim: int, n_heads: int, n_layers: int, dropout: float):
        super().__init__()
        layer = nn.TransformerEncoderLayer(
            embed_dim, n_heads, 4 * embed_dim, dropout, "relu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(
            layer, n_layers, norm=nn.LayerNorm(embed_dim), enable_nested_tensor=False
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mask = nn.Transformer.generate_square_subsequent_mask(x.shape[1], device=x.device)
        return self.encoder(x, mask=mask, is_causal=True)


def with_torch_encoder(agent: DecisionTransformer, hyperparameters: dict) -> DecisionTransformer:
    """``agent`` with torch's encoder for its blocks, and a new optimizer over the new weights."""
    h = hyperparameters
    model = agent.model
    model.blocks = TorchEncoderBlocks(h["embed_dim"], h["n_heads"], h["n_layers"], h["dropout"])
    model.final_ln = nn.Identity()
    model.to(agent.device)
    agent.optimizer = torch.optim.AdamW(
        model.parameters(), lr=h["lr"], weight_decay=h["weight_decay"], fused=True
    )
    agent.scheduler = torch.optim.lr_scheduler.LambdaLR(agent.optimizer, lambda step: 1.0)
    return agent


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", default="cpu", help="comma-separated, e.g. cpu,cuda")
    parser.add_argument("--reps", type=int, default=5, help="alternating rounds")
    parser.add_argument("--steps", type=int, default=20, help="gradient steps per round")
    parser.add_argument(
        "--compile", action="store_true", help="also the model through torch.compile"
    )
    args = parser.parse_args()
    data = walker2d_shaped_data()
    hyperparameters = defaults_for(DecisionTransformer, max_episode_steps=STEPS)

    def agent(device: str, precision: str = "fp32") -> DecisionTransformer:
        return DecisionTransformer(
            OBS,
            [-1.0] * ACT,
            [1.0] * ACT,
            dataset=data,
            device=device,
            **hyperparameters | {"precision": precision},
        )

    agents = {}
    for device in args.devices.split(","):
        agents[f"walkers DT on {device}"] = agent(device)
        agents[f"walkers DT, precision=bf16, on {device}"] = agent(device, "bf16")
        agents[f"torch TransformerEncoder on {device}"] = with_torch_encoder(
            agent(device), hyperparameters
        )
        if args.compile:
            compiled = agent(device)
            compiled.model = torch.compile(compiled.model)  # the optimizer keeps its parameters
            agents[f"walkers DT, model through torch.compile, on {device}"] = compiled

    def ms_per_step(agent) -> float:
        sync = torch.cuda.synchronize if agent.device.type == "cuda" else (lambda: None)
        sync()
        start = time.perf_counter()
        for _ in range(args.steps):
            agent.update()
        sync()
        return (time.perf_counter() - start) / args.steps * 1e3

    for agent in agents.values():
        ms_per_step(agent)  # warm-up: allocations, kernels, the first AdamW step
    times = alternate(agents, ms_per_step, args.reps)
    first = next(iter(agents))
    print(
        f"\nDecision Transformer gradient step, Walker2d shapes, reference size, "
        f"{torch.get_num_threads()} CPU threads, {args.reps} rounds x {args.steps} steps"
    )
    print_table(times, "ms per step", baseline=first)


if __name__ == "__main__":
    main()
