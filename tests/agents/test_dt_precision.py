"""``algo.precision=bf16``: the Decision Transformer under bfloat16 autocast, an opt-in for speed
(README, Offline RL). Its matmuls run in bfloat16 while the weights, the optimizer and the loss
stay fp32; it learns the same thing to bfloat16's rounding, and a typo is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import compose_cfg, tiny_offline_data
from walkers.agents.base import cpu_has_native_bf16
from walkers.agents.dt import DecisionTransformer
from walkers.agents.factory import defaults_for
from walkers.errors import ConfigError
from walkers.training.settings import validate

SMALL = {
    "context_length": 4,
    "embed_dim": 16,
    "n_layers": 1,
    "dropout": 0.0,
    "batch_size": 8,
    "warmup_steps": 1,
    "max_episode_steps": 50,
}


def _agent(precision: str, **overrides) -> DecisionTransformer:
    hyperparameters = defaults_for(DecisionTransformer, precision=precision, **SMALL | overrides)
    return DecisionTransformer(
        3, [-2.0], [2.0], dataset=tiny_offline_data(), seed=0, **hyperparameters
    )


def _mlp_output_dtypes(agent: DecisionTransformer) -> list[torch.dtype]:
    """The dtypes the first block's MLP produces during the agent's next calls."""
    seen = []
    agent.model.blocks[0].mlp[0].register_forward_hook(lambda m, i, out: seen.append(out.dtype))
    return seen


@pytest.mark.parametrize("precision, dtype", [("fp32", torch.float32), ("bf16", torch.bfloat16)])
def test_the_transformer_runs_in_the_declared_precision_with_fp32_weights(precision, dtype):
    agent = _agent(precision)
    seen = _mlp_output_dtypes(agent)
    metrics = agent.update()
    action = agent.act(np.zeros(3, dtype=np.float32))
    assert seen == [dtype, dtype]  # the update's forward pass and the action's
    assert all(p.dtype == torch.float32 for p in agent.model.parameters())
    assert all(
        s.dtype == torch.float32
        for state in agent.optimizer.state.values()
        for s in state.values()
        if s.is_floating_point()
    )
    assert metrics["loss/action"].dtype == torch.float32 and torch.isfinite(metrics["loss/action"])
    assert action.dtype == np.float32 and np.all(np.abs(action) <= 2.0)


def test_bf16_learns_what_fp32_learns_to_its_rounding():
    """From the same weights, on the same batches: the held-out loss falls alike in both."""
    fp32, bf16 = _agent("fp32", lr=1e-3), _agent("bf16", lr=1e-3)
    batch = fp32.sampler.sample(64)

    def loss(agent: DecisionTransformer) -> float:
        agent.model.eval()
        with torch.no_grad():
            predicted = agent.model(batch.returns_to_go, batch.obs, batch.actions, batch.timesteps)
        squared_error = (predicted - batch.actions).pow(2).mean(dim=-1) * batch.mask
        return (squared_error.sum() / batch.mask.sum()).item()

    start = loss(fp32)
    assert loss(bf16) == start
    for _ in range(100):
        fp32.update(), bf16.update()
    learned = start - loss(fp32)
    assert learned > 0.7 * start  # (measured: 0.54 -> 0.10)
    assert abs(loss(bf16) - loss(fp32)) < 0.1 * learned  # (measured: 0.106 against 0.103)


def test_an_unknown_precision_is_refused_in_one_line():
    with pytest.raises(
        ConfigError, match=r"^algo.precision='fp16' is not allowed: must be fp32 or bf16"
    ):
        validate(compose_cfg(["algo=dt", "env=pendulum", "dataset=x", "algo.precision=fp16"]))


EPYC_FLAGS = "flags\t\t: fpu vme sse sse2 avx avx2 avx512f avx512bw avx512vl avx512_vnni"


@pytest.mark.parametrize(
    "cpuinfo, native",
    [
        (f"processor\t: 0\n{EPYC_FLAGS}\n", False),
        (f"processor\t: 0\n{EPYC_FLAGS} avx512_bf16\n", True),
        (f"processor\t: 0\n{EPYC_FLAGS} amx_bf16 amx_tile\n", True),
        ("processor\t: 0\nFeatures\t: fp asimd bf16 sve\n", None),  # ARM: not told here
    ],
)
def test_native_bfloat16_is_read_from_the_cpu_flags(cpuinfo, native):
    assert cpu_has_native_bf16(cpuinfo) is native


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_bf16_on_a_cpu_that_emulates_it_is_named_at_the_start(precision, caplog):
    with caplog.at_level("WARNING", logger="walkers"):
        _agent(precision)
    emulated = precision == "bf16" and cpu_has_native_bf16() is False
    assert ("bfloat16 is emulated here" in caplog.text) is emulated
    if emulated:
        assert "algo.precision=fp32" in caplog.text
