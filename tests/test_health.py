"""The NaN/inf guard: a finite loss with a non-finite gradient is skipped like a NaN loss, an
actor skipped again and again counts toward ``divergence_patience``, and a checkpoint keeps
every torch generator the updates draw from (the CUDA ones when a run trains on CUDA)."""

from __future__ import annotations

import logging

import numpy as np
import torch

from tests.conftest import TINY, compose_cfg
from walkers.agents.base import Transition
from walkers.agents.factory import build_agent
from walkers.agents.health import SKIPPED, SKIPPED_IN_A_ROW, guarded_step
from walkers.seeding import restore_torch_rng, torch_rng_state
from walkers.train import train
from walkers.training import checkpoints
from walkers.training.envs import env_spaces, make_env


def _sqrt_members(start: list[float]):
    """Members whose loss sqrt(w) is finite everywhere but has an infinite gradient at w=0."""
    w = torch.nn.Parameter(torch.tensor(start).unsqueeze(-1))
    return w, torch.optim.Adam([w], lr=0.1, fused=True)


def test_a_finite_loss_with_an_infinite_gradient_skips_that_member_only():
    w, optimizer = _sqrt_members([0.0, 4.0])
    loss = w.squeeze(-1).sqrt()
    assert torch.isfinite(loss).all()
    bad = guarded_step(optimizer, loss, copies=1)
    assert bad.tolist() == [1.0, 0.0]
    assert w[0].item() == 0.0 and w[1].item() != 4.0  # member 0 untouched, member 1 stepped


def test_a_single_agent_with_an_infinite_gradient_takes_no_step():
    w, optimizer = _sqrt_members([0.0])
    bad = guarded_step(optimizer, w.squeeze(-1).sqrt(), copies=1)
    assert bad.tolist() == [1.0] and w.item() == 0.0
    assert all(torch.isfinite(s).all() for s in optimizer.state[w].values())  # moments clean


def _td3_with_a_broken_actor(patience_updates: int = 12):
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.hidden_sizes=[16,16]",
                       "algo.learning_starts=8", "algo.batch_size=8"])  # fmt: skip
    env = make_env(cfg.env)
    agent = build_agent(cfg, env_spaces(env))
    obs, _ = env.reset(seed=0)
    for _ in range(16):
        action = env.action_space.sample()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        over = terminated or truncated
        agent.observe(Transition(obs, action, reward, next_obs, terminated, over))
        obs = next_obs
    env.close()
    real_actor_loss = agent._actor_loss

    def nan_actor_loss(obs, noise):  # a fault in the actor's step alone; the critic's is sound
        loss, info = real_actor_loss(obs, noise)
        return loss * float("nan"), info

    agent._actor_loss = nan_actor_loss
    return agent, [agent.update() for _ in range(patience_updates)]


def test_an_actor_skipped_again_and_again_counts_toward_divergence():
    agent, metrics = _td3_with_a_broken_actor()
    assert agent.policy_delay == 2
    critic = [m["loss/critic"].item() for m in metrics]
    assert all(np.isfinite(critic))  # the critic learns on; only the actor's steps are skipped
    # from the first actor step (update 2) on, every update counts: nothing proves it recovered
    in_a_row = [m[SKIPPED_IN_A_ROW].item() for m in metrics]
    assert in_a_row == [0.0] + [float(i) for i in range(1, len(metrics))]
    assert metrics[-1][SKIPPED].item() == len(metrics) - 1
    restored = agent.guard.state_dict()
    agent.guard.load_state_dict({k: [0.0] for k in restored})
    agent.guard.load_state_dict(restored)  # the delayed step's verdict survives a checkpoint
    assert agent.update()[SKIPPED_IN_A_ROW].item() == len(metrics)


def test_a_checkpoint_keeps_the_cpu_generator_and_a_slot_for_cuda(store):
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.hidden_sizes=[16,16]",
                       "algo.learning_starts=100", *TINY, *store["overrides"]])  # fmt: skip
    train(cfg)
    (last,) = (store["path"] / "work").glob("runs/*/checkpoints/last.pt")
    state = checkpoints.load(last)
    assert state["torch_rng"].dtype == torch.uint8 and state["torch_rng"].numel() > 0
    # on CPU no CUDA generator was used: nothing to keep; on CUDA one state per device
    expected = torch.cuda.device_count() if torch.cuda.is_initialized() else None
    assert (state["cuda_rng"] is None) == (expected is None)


def test_cuda_generators_are_restored_where_the_devices_match_else_said(caplog):
    state = torch_rng_state()
    draws = torch.rand(3)
    restore_torch_rng(state)
    assert torch.equal(torch.rand(3), draws)  # the CPU generator is back where it was
    if torch.cuda.is_available():  # a GPU machine: every device's generator round-trips
        torch.cuda.init()
        state = torch_rng_state()
        assert len(state["cuda_rng"]) == torch.cuda.device_count()
        on_gpu = torch.rand(3, device="cuda")
        restore_torch_rng(state)
        assert torch.equal(torch.rand(3, device="cuda"), on_gpu)
    foreign = state | {"cuda_rng": [torch.zeros(16, dtype=torch.uint8)] * 9}  # 9 devices
    with caplog.at_level(logging.WARNING, logger="walkers"):
        restore_torch_rng(foreign)
    assert "CUDA random state (9 devices) cannot be restored" in caplog.text
