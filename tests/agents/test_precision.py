"""``algo.precision=bf16`` for TD3, DDPG and SAC: the update under bfloat16 autocast, an arm of its
own (docs/speed.md). The hidden layers' matmuls run in bfloat16; each network's output layer, the
losses, the weights and Adam stay fp32; acting stays fp32. It learns what fp32 learns to
bfloat16's rounding, compiled or not, and is refused where it cannot run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import compose_cfg
from walkers.agents.base import Transition
from walkers.agents.factory import defaults_for
from walkers.agents.sac import SAC
from walkers.agents.sb3.arguments import sb3_arguments
from walkers.agents.td3 import TD3
from walkers.errors import ConfigError
from walkers.training.settings import validate

OBS, ACT = 5, 2
SMALL = {"hidden_sizes": [32, 32], "batch_size": 32, "learning_starts": 0, "buffer_size": 2000}


def _agent(cls, precision: str, **overrides):
    agent = cls(
        OBS,
        [-1.0] * ACT,
        [1.0] * ACT,
        seed=0,
        **defaults_for(cls, precision=precision, **SMALL) | overrides,
    )
    rng = np.random.default_rng(0)  # the same transitions for every agent
    for _ in range(500):
        obs = rng.normal(size=OBS).astype(np.float32)
        action = rng.uniform(-1, 1, ACT).astype(np.float32)
        reward = float(obs[0] - action[0] ** 2)
        agent.observe(Transition(obs, action, reward, obs, False, False))
    return agent


def _output_dtypes(network: torch.nn.Module, seen: list) -> None:
    """Note the dtype each of the network's layers produces from now on."""
    for name, layer in network.named_modules():
        if hasattr(layer, "head"):
            layer.register_forward_hook(lambda m, i, out, n=name: seen.append((n, out.dtype)))


@pytest.mark.parametrize("cls", [TD3, SAC])
def test_bf16_runs_the_hidden_matmuls_in_bfloat16_and_the_heads_losses_and_weights_in_fp32(cls):
    agent = _agent(cls, "bf16")
    seen = []
    _output_dtypes(agent.critic, seen)
    metrics = agent.update()
    hidden = {dtype for name, dtype in seen if name.startswith("hidden")}
    heads = {dtype for name, dtype in seen if name == "out"}
    assert hidden == {torch.bfloat16} and heads == {torch.float32}
    assert all(v.dtype == torch.float32 and torch.isfinite(v).all() for v in metrics.values())
    parts = (agent.actor, agent.critic, agent.critic_target)
    assert all(p.dtype == torch.float32 for part in parts for p in part.parameters())
    assert all(
        s.dtype == torch.float32
        for state in agent.critic_optimizer.state.values()
        for s in state.values()
        if s.is_floating_point()
    )
    acted = []
    _output_dtypes(agent.actor, acted)
    action = agent.act(np.zeros(OBS, dtype=np.float32), explore=False)
    assert {dtype for _, dtype in acted} == {torch.float32}  # acting is not under autocast
    assert action.dtype == np.float32


@pytest.mark.parametrize(("cls", "compile"), [(TD3, False), (SAC, False), (TD3, True)])
def test_bf16_learns_what_fp32_learns_to_its_rounding(cls, compile):
    """From the same weights, on the same batches and noise: the critics move alike."""
    fp32, bf16 = _agent(cls, "fp32"), _agent(cls, "bf16", compile=compile)
    probe = fp32.sample()  # a fixed batch to read Q on

    def mean_q(agent) -> float:
        with torch.no_grad():
            return agent.q_values(agent.critic, probe.obs, probe.action).mean().item()

    start = mean_q(fp32)
    assert mean_q(bf16) == start
    for _ in range(150):
        fp32.update(), bf16.update()
    moved = mean_q(fp32) - start
    assert abs(moved) > 0.1  # the critics learned something to compare
    assert abs(mean_q(bf16) - mean_q(fp32)) < 0.1 * abs(moved)


def test_an_unknown_precision_is_refused_in_one_line():
    with pytest.raises(
        ConfigError, match=r"^algo.precision='fp16' is not allowed: must be fp32 or bf16"
    ):
        validate(compose_cfg(["algo=td3", "env=pendulum", "algo.precision=fp16"]))


def test_sb3_twins_refuse_bf16_in_one_line():
    hyperparameters = defaults_for(TD3, precision="bf16")
    with pytest.raises(ConfigError, match=r"^algo.precision='bf16' cannot be expressed"):
        sb3_arguments("td3", hyperparameters)
