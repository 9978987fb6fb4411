"""TD7: update after update against the authors' code, and its parts against their definitions.

The authors' code (github.com/sfujim/TD7, ``TD7.py`` and ``buffer.py``) is not a package, so the
side-by-side test reads it from a checkout named by ``TD7_REFERENCE`` and skips without one:

    git clone https://github.com/sfujim/TD7 /tmp/TD7
    TD7_REFERENCE=/tmp/TD7 .venv/bin/python -m pytest tests/agents/test_td7.py

The other tests hold LAP's loss, sampling and priorities, the hard target updates, the value
clipping and the checkpoint of the prioritised buffer to what the paper defines.
"""

from __future__ import annotations

import importlib
import os
import sys

import numpy as np
import pytest
import torch

from tests.conftest import filled_agent
from walkers.agents.base import Transition
from walkers.agents.factory import defaults_for
from walkers.agents.td7 import TD7, PrioritizedReplay, avg_l1_norm, lap_huber

REFERENCE = os.environ.get("TD7_REFERENCE")
OBS, ACT = 6, 3


def test_avg_l1_norm_divides_by_the_mean_absolute_value():
    x = torch.tensor([[1.0, -3.0, 2.0, 2.0], [0.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(avg_l1_norm(x)[0].numpy(), [0.5, -1.5, 1.0, 1.0])
    assert torch.equal(avg_l1_norm(x)[1], x[1])  # zeros stay zeros (the clamp at eps)


def test_lap_huber_is_quadratic_below_the_least_priority_and_linear_above():
    td = torch.tensor([[[0.5, 2.0], [1.0, 0.0]]])  # (K=1, C=2, N=2)
    # per transition, summed over critics: 0.125 + 1.0 = 1.125 and 2.0 + 0 = 2.0; mean 1.5625
    assert lap_huber(td, 1.0).item() == pytest.approx(1.5625)
    assert lap_huber(td, 4.0).item() == pytest.approx((0.125 + 0.5 + 2.0) / 2)


def test_lap_samples_in_proportion_to_priority_and_new_rows_get_the_largest():
    buffer = PrioritizedReplay(100, 1, 1, seeds=(0, 1))
    for t in range(4):
        buffer.add([[t], [t]], [[0.0], [0.0]], [0.0, 0.0], [[0], [0]], [0.0, 0.0])
    idx = torch.tensor([[1, 2], [3, 3]])
    buffer.update_priority(idx, torch.tensor([[3.0, 2.0], [5.0, 5.0]]), keep=torch.zeros(2))
    assert buffer.priority[0, :4].tolist() == [1.0, 3.0, 2.0, 1.0]
    assert buffer.max_priority.tolist() == [3.0, 5.0]
    buffer.add([[9], [9]], [[0.0], [0.0]], [0.0, 0.0], [[0], [0]], [0.0, 0.0])
    assert buffer.priority[:, 4].tolist() == [3.0, 5.0]  # a new row: the member's largest
    rows = buffer.sample(40_000).index
    assert rows.max() < 5  # never an unfilled row
    freq = torch.bincount(rows[0], minlength=5).double() / rows.shape[1]
    np.testing.assert_allclose(freq.numpy(), np.array([1, 3, 2, 1, 3]) / 10, atol=0.01)
    # a member whose critics' step was skipped keeps its priorities
    buffer.update_priority(idx, torch.full((2, 2), 7.0), keep=torch.tensor([1.0, 0.0]))
    assert buffer.priority[0, 1:3].tolist() == [3.0, 2.0] and buffer.priority[1, 3] == 7.0
    buffer.reset_max_priority()
    assert buffer.max_priority.tolist() == [3.0, 7.0]


def test_the_prioritised_buffer_checkpoints_its_priorities():
    agent = filled_agent(TD7, population=2, **tiny_td7())
    for _ in range(5):
        agent.update()
    state = agent.state_dict(with_buffer=True)
    again = filled_agent(TD7, population=2, buffer_size=500, **tiny_td7())
    again.buffer.priority.zero_()
    again.load_state_dict(state)
    assert torch.equal(again.buffer.priority, agent.buffer.priority)
    assert torch.equal(again.buffer.max_priority, agent.buffer.max_priority)
    assert torch.equal(again.value_clip.seen_high, agent.value_clip.seen_high)
    # the next update is the same update
    a, b = agent.update(), again.update()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_targets_move_by_hard_copies_every_target_update_rate_updates():
    agent = filled_agent(TD7, **tiny_td7(target_update_rate=4))

    def same(target, source):
        pairs = zip(target.parameters(), source.parameters(), strict=True)
        return all(torch.equal(t, s) for t, s in pairs)

    for n in range(1, 9):
        agent.update()
        due = n % 4 == 0
        assert same(agent.critic_target, agent.critic) == due
        assert same(agent.actor.encoder, agent.encoder) == due  # f_t <- f
        if due:  # the clip's bounds become the range of the targets seen so far
            assert agent.value_clip.high == agent.value_clip.seen_high
            assert agent.value_clip.low == agent.value_clip.seen_low
    assert agent.value_clip.low < agent.value_clip.high


def tiny_td7(**settings) -> dict:
    return {"zs_dim": 8, "encoder_hidden_sizes": [16, 16], "target_update_rate": 3} | settings


# --- side by side with the authors' code -------------------------------------------------------
def actor_layers(ours, theirs) -> list:
    """(our ensemble layer, member, their nn.Linear) of the same layer, in the actor."""
    mine = [ours.state_layer, *ours.layers]
    theirs_layers = (theirs.l0, theirs.l1, theirs.l2, theirs.l3)
    return [(m, 0, t) for m, t in zip(mine, theirs_layers, strict=True)]


def critic_layers(ours, theirs) -> list:
    mine = [ours.state_action_layer, *ours.layers]
    twins = ((theirs.q01, theirs.q1, theirs.q2, theirs.q3),
             (theirs.q02, theirs.q4, theirs.q5, theirs.q6))  # fmt: skip
    return [(m, k, t) for k, twin in enumerate(twins) for m, t in zip(mine, twin, strict=True)]


def encoder_layers(ours, theirs) -> list:
    mine = [*ours.state_layers, *ours.state_action_layers]
    names = (theirs.zs1, theirs.zs2, theirs.zs3, theirs.zsa1, theirs.zsa2, theirs.zsa3)
    return [(m, 0, t) for m, t in zip(mine, names, strict=True)]


def same_layers(agent: TD7, ref) -> list:
    """Every layer of walkers' TD7 beside the authors' (their Linear (out, in) is our (in, out))."""
    return [
        *actor_layers(agent.actor, ref.actor),
        *actor_layers(agent.actor_target, ref.actor_target),
        *critic_layers(agent.critic, ref.critic),
        *critic_layers(agent.critic_target, ref.critic_target),
        *encoder_layers(agent.encoder, ref.encoder),
        *encoder_layers(agent.actor.encoder, ref.fixed_encoder),
        *encoder_layers(agent.actor_target.encoder, ref.fixed_encoder_target),
    ]


@pytest.mark.skipif(not REFERENCE, reason="TD7_REFERENCE: a checkout of github.com/sfujim/TD7")
def test_updates_match_the_authors_td7(monkeypatch):
    """The same initial weights, transitions, batches and smoothing noise: after each update the
    authors' and walkers' priorities and value-clipping range agree, and after 8 updates (4
    actor steps, 2 hard target updates) every network's weights."""
    monkeypatch.syspath_prepend(REFERENCE)
    sys.modules.pop("buffer", None)
    reference = importlib.import_module("TD7")
    hp = reference.Hyperparameters(
        batch_size=64, target_update_rate=3, zs_dim=16, enc_hdim=32, critic_hdim=32, actor_hdim=32
    )
    torch.manual_seed(0)
    ref = reference.Agent(OBS, ACT, max_action=1.0, hp=hp)
    sizes = {"hidden_sizes": [32, 32], "zs_dim": 16, "encoder_hidden_sizes": [32, 32]}
    settings = {"batch_size": 64, "target_update_rate": 3, "learning_starts": 0, **sizes}
    agent = TD7(OBS, [-1.0] * ACT, [1.0] * ACT, **defaults_for(TD7, buffer_size=1000, **settings))
    with torch.no_grad():
        for ours, k, theirs in same_layers(agent, ref):
            ours.weight[k] = theirs.weight.T
            ours.bias[k, 0] = theirs.bias

    rng = np.random.default_rng(0)
    for t in range(300):
        s, s2 = rng.normal(size=(2, OBS)).astype(np.float32)
        a = rng.uniform(-1, 1, ACT).astype(np.float32)
        r, done = float(rng.normal()), t % 40 == 39
        ref.replay_buffer.add(s, a, s2, r, float(done))
        agent.observe(Transition(s, a, r, s2, done, done))

    shared = {}
    our_sample, our_noise = agent.buffer.sample, agent.noise_like

    def sample(n):  # walkers draws by its priorities; the authors' buffer takes the same rows
        batch = our_sample(n)
        shared["ind"] = batch.index[0].numpy()
        return batch

    def noise_like(x):
        shared["eps"] = our_noise(x)
        return shared["eps"]

    def reference_sample():
        buf = ref.replay_buffer
        buf.ind = shared["ind"]
        return tuple(
            torch.tensor(column[buf.ind], dtype=torch.float)
            for column in (buf.state, buf.action, buf.next_state, buf.reward, buf.not_done)
        )

    monkeypatch.setattr(agent.buffer, "sample", sample)
    monkeypatch.setattr(agent, "noise_like", noise_like)
    monkeypatch.setattr(ref.replay_buffer, "sample", reference_sample)
    for _ in range(8):
        agent.update()
        with monkeypatch.context() as m:  # their only random draw: the smoothing noise
            m.setattr(torch, "randn_like", lambda x: shared["eps"][0])
            ref.train()
        ind = shared["ind"]
        np.testing.assert_allclose(
            agent.buffer.priority[0, ind].numpy(), ref.replay_buffer.priority[ind].numpy(),
            rtol=1e-4,
        )  # fmt: skip
        assert agent.buffer.max_priority.item() == pytest.approx(
            ref.replay_buffer.max_priority, rel=1e-4
        )
        assert agent.value_clip.seen_high.item() == pytest.approx(ref.max, rel=1e-4)
        assert agent.value_clip.seen_low.item() == pytest.approx(ref.min, rel=1e-4)
    assert agent.num_updates == ref.training_steps == 8
    assert agent.value_clip.high.item() == pytest.approx(ref.max_target, rel=1e-4)

    for ours, k, theirs in same_layers(agent, ref):
        for got, want in ((ours.weight[k], theirs.weight.T), (ours.bias[k, 0], theirs.bias)):
            np.testing.assert_allclose(got.detach(), want.detach(), rtol=1e-4, atol=1e-5)
