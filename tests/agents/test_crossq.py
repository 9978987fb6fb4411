"""CrossQ's own parts (walkers/agents/crossq.py, walkers/agents/common/renorm.py): Batch
Renormalization by hand, in its warm-up and past it; the critics' one joint pass over now and
next, whose statistics are those of the mixture; the actor's over now alone; acting in running
statistics. What CrossQ shares with SAC (reproducibility, populations, the NaN guard, compile,
checkpoints) is tested with SAC's in test_sac.py; its parity with sb3-contrib's CrossQ in
test_parity.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from walkers.agents.base import Transition
from walkers.agents.common.renorm import EnsembleBatchRenorm
from walkers.agents.crossq import CrossQ
from walkers.agents.factory import defaults_for

MOMENTUM = 0.1


def renorm(warmup_steps: int = 5) -> EnsembleBatchRenorm:
    layer = EnsembleBatchRenorm(2, 3, momentum=MOMENTUM, warmup_steps=warmup_steps, eps=1e-8)
    with torch.no_grad():  # a scale and shift that are not the identity
        layer.scale.copy_(torch.tensor([1.5, 0.5, 2.0]).expand(2, 1, 3))
        layer.bias.copy_(torch.tensor([0.1, -0.2, 0.3]).expand(2, 1, 3))
    return layer


def batch(seed: int = 0) -> torch.Tensor:
    """(2 members, 64 rows, 3 features), each member's features off-centre and scaled."""
    g = torch.Generator().manual_seed(seed)
    return 4.0 * torch.randn(2, 64, 3, generator=g) + torch.tensor([[[1.0, -2.0, 3.0]]])


# --- Batch Renormalization (Ioffe 2017) ----------------------------------------------------------
def test_in_its_warm_up_it_normalizes_with_the_batch_and_moves_the_running_statistics():
    layer, x = renorm(), batch()
    layer.train()
    y = layer(x)
    mean, var = x.mean(dim=1, keepdim=True), x.var(dim=1, keepdim=True)
    torch.testing.assert_close(y, layer.scale * (x - mean) / var.sqrt() + layer.bias)
    torch.testing.assert_close(layer.running_mean, MOMENTUM * mean)  # from 0
    torch.testing.assert_close(layer.running_var, (1 - MOMENTUM) + MOMENTUM * var)  # from 1
    assert layer.steps.tolist() == [1, 1]


@pytest.mark.parametrize("running_var", [4.0, 0.01], ids=["r-inside-its-clip", "r-clipped"])
def test_past_its_warm_up_it_corrects_the_batch_towards_the_running_statistics(running_var):
    """x^ = (x - mu_B) / sigma_B * r + d, r = clip(sigma_B / sigma, 1/3, 3), d = clip((mu_B - mu)
    / sigma, -5, 5): the paper's Algorithm 1, with sb3-contrib's clips."""
    layer, x = renorm(warmup_steps=5), batch()
    with torch.no_grad():
        layer.running_mean.fill_(0.5)
        layer.running_var.fill_(running_var)
        layer.steps.fill_(6)
    sigma = layer.running_var.sqrt()
    mu_b, sigma_b = x.mean(dim=1, keepdim=True), x.var(dim=1, keepdim=True).sqrt()
    r = (sigma_b / sigma).clamp(1 / 3, 3)
    d = ((mu_b - layer.running_mean) / sigma).clamp(-5, 5)
    assert (r == 3).any() == (running_var == 0.01)  # the clip is reached where it should be
    layer.train()
    y = layer(x)
    expected = layer.scale * ((x - mu_b) / sigma_b * r + d) + layer.bias
    torch.testing.assert_close(y, expected, rtol=1e-5, atol=1e-5)


def test_in_evaluation_it_normalizes_with_the_running_statistics_and_moves_nothing():
    layer, x = renorm(), batch()
    with torch.no_grad():
        layer.running_mean.fill_(0.5)
        layer.running_var.fill_(4.0)
    before = {k: v.clone() for k, v in layer.state_dict().items()}
    layer.eval()
    torch.testing.assert_close(layer(x), layer.scale * (x - 0.5) / 2.0 + layer.bias)
    for key, value in layer.state_dict().items():
        assert torch.equal(value, before[key]), key
    member = layer(x[1:], members=slice(1, 2))  # one member alone: its own slice
    torch.testing.assert_close(member, layer(x)[1:])


# --- the agent's passes --------------------------------------------------------------------------
OBS, NOW, NEXT = 3, np.array([1.0, -2.0, 4.0]), np.array([3.0, 2.0, -4.0])


def first_update() -> CrossQ:
    """A CrossQ after its first update, every transition from NOW to NEXT (so any batch is)."""
    settings = defaults_for(
        CrossQ,
        batch_size=16,
        learning_starts=20,
        buffer_size=100,
        hidden_sizes=[16, 16],
        critic_hidden_sizes=[16, 16],
        renorm_momentum=MOMENTUM,
        policy_delay=1,
    )
    agent = CrossQ(OBS, [-1.0], [1.0], seed=0, **settings)
    for _ in range(20):
        agent.observe(Transition(NOW, np.array([0.5]), 1.0, NEXT, False, False))
    assert agent.num_updates == 0 and agent.update() and agent.num_updates == 1
    return agent


def test_the_critics_normalize_one_joint_batch_of_now_and_next():
    """The critics' statistics are those of [(s, a); (s', a')] together: over the obs features,
    the mean of NOW and NEXT, and their spread; a pass over (s, a) alone would give NOW and 0."""
    agent = first_update()
    first = agent.critic.norms[0]  # before the first layer, on [s, a]
    rows = 2 * 16
    joint_mean = torch.tensor((NOW + NEXT) / 2, dtype=torch.float32)
    joint_var = torch.tensor(((NOW - NEXT) / 2) ** 2 * rows / (rows - 1), dtype=torch.float32)
    for member in range(first.running_mean.shape[0]):  # the two critics
        torch.testing.assert_close(first.running_mean[member, 0, :OBS], MOMENTUM * joint_mean)
        torch.testing.assert_close(
            first.running_var[member, 0, :OBS], (1 - MOMENTUM) + MOMENTUM * joint_var
        )
    assert first.steps.tolist() == [1, 1]  # one training pass: the actor's step read them frozen


def test_the_actor_normalizes_the_batch_of_now_alone():
    agent = first_update()
    first = agent.actor.norms[0]  # on s
    now = torch.tensor(NOW, dtype=torch.float32)
    torch.testing.assert_close(first.running_mean[0, 0], MOMENTUM * now)
    torch.testing.assert_close(first.running_var[0, 0], torch.full((OBS,), 1 - MOMENTUM))
    assert first.steps.tolist() == [1]  # the target's a' ~ pi(.|s') came in running statistics


def test_acting_uses_the_running_statistics_and_moves_none():
    agent = first_update()

    def statistics() -> dict[str, torch.Tensor]:
        return {
            f"{network}.{name}": value.clone()
            for network in ("actor", "critic")
            for name, value in getattr(agent, network).state_dict().items()
            if "running" in name or name.endswith("steps")
        }

    before = statistics()
    one = agent.act(NOW, explore=False)  # a batch of one: batch statistics would be undefined
    assert np.isfinite(one).all() and np.array_equal(one, agent.act(NOW, explore=False))
    agent.act(NEXT, explore=True)
    assert len(before) == 2 * 3 * 3  # actor and critics: 3 renormalizations, 3 statistics each
    for name, value in statistics().items():
        assert torch.equal(value, before[name]), name
