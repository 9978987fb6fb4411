"""The NaN/inf guard: a finite loss with a non-finite gradient is skipped like a NaN loss, an
actor skipped again and again counts toward ``divergence_patience``, PPO, the Decision
Transformer and REINFORCE (its baseline too) skip a non-finite update through the same guard and
step normally after it, and a checkpoint keeps every torch generator the updates draw from (the
CUDA ones when a run trains on CUDA)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from tests.conftest import TINY, compose_cfg, tiny_offline_data
from walkers.agents.base import Transition
from walkers.agents.common.functional import guarded_adam_step
from walkers.agents.common.health import (
    SKIPPED,
    SKIPPED_IN_A_ROW,
    clip_or_skip,
    skip_nonfinite,
)
from walkers.agents.dt import DecisionTransformer
from walkers.agents.factory import build_agent, defaults_for
from walkers.agents.ppo import PPO
from walkers.agents.reinforce import Reinforce
from walkers.seeding import restore_torch_rng, torch_rng_state
from walkers.train import train
from walkers.training.envs import env_spaces, make_env
from walkers.training.run import read_checkpoint


def _sqrt_members(start: list[float]):
    """Members whose loss sqrt(w) is finite everywhere but has an infinite gradient at w=0."""
    w = torch.nn.Parameter(torch.tensor(start).unsqueeze(-1))
    return w, torch.optim.Adam([w], lr=0.1, fused=True)


def _guarded_step(optimizer, member_loss) -> torch.Tensor:
    """The step as every off-policy update writes it, the guard between backward and step."""
    optimizer.zero_grad(set_to_none=True)
    member_loss.sum().backward()
    skipped = skip_nonfinite(optimizer, member_loss)
    optimizer.step()
    return skipped


def _functional_step(optimizer, member_loss) -> torch.Tensor:
    """The same step as a compiled update takes it (``compile=true`` on the CPU)."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    grads = torch.autograd.grad(member_loss.sum(), params)
    return guarded_adam_step(optimizer, list(grads), member_loss.detach())


GUARDED_STEPS = pytest.mark.parametrize("step", [_guarded_step, _functional_step])


@GUARDED_STEPS
def test_a_finite_loss_with_an_infinite_gradient_skips_that_member_only(step):
    w, optimizer = _sqrt_members([0.0, 4.0])
    loss = w.squeeze(-1).sqrt()
    assert torch.isfinite(loss).all()
    bad = step(optimizer, loss)
    assert bad.tolist() == [1.0, 0.0]
    assert w[0].item() == 0.0 and w[1].item() != 4.0  # member 0 untouched, member 1 stepped


@GUARDED_STEPS
def test_a_single_agent_with_an_infinite_gradient_takes_no_step(step):
    w, optimizer = _sqrt_members([0.0])
    bad = step(optimizer, w.squeeze(-1).sqrt())
    assert bad.tolist() == [1.0] and w.item() == 0.0
    assert all(torch.isfinite(s).all() for s in optimizer.state[w].values())  # moments clean


def test_the_functional_adam_step_is_fused_adams():
    """Three steps of members (1, 4) with the loss sqrt(w): the compiled update's Adam, written
    as tensor ops, moves the weights and moments as torch's fused Adam does."""
    (w1, eager), (w2, functional) = _sqrt_members([1.0, 4.0]), _sqrt_members([1.0, 4.0])
    for _ in range(3):
        _guarded_step(eager, w1.squeeze(-1).sqrt())
        _functional_step(functional, w2.squeeze(-1).sqrt())
    torch.testing.assert_close(w2, w1)
    for key in ("step", "exp_avg", "exp_avg_sq"):
        torch.testing.assert_close(functional.state[w2][key], eager.state[w1][key])


def guarded_agent_step(optimizer, loss, max_grad_norm, scheduler=None):
    """One agent's step as PPO, REINFORCE and the Decision Transformer write it."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    skipped, grad_norm = clip_or_skip(optimizer, loss, max_grad_norm)
    optimizer.step()
    if scheduler is not None:
        scheduler.step()
    return skipped, grad_norm


def test_an_agent_step_clips_like_clip_grad_norm_and_returns_the_norm_before():
    w = torch.nn.Parameter(torch.tensor([3.0, 4.0]))
    optimizer = torch.optim.SGD([w], lr=1.0, fused=True)
    skipped, grad_norm = guarded_agent_step(optimizer, (w * w).sum() / 2, max_grad_norm=1.0)
    assert skipped.item() == 0.0 and grad_norm.item() == 5.0  # the gradient is w: norm 5
    assert torch.allclose(w, torch.tensor([3.0 - 0.6, 4.0 - 0.8]))  # a step of norm 1


def test_a_skipped_agent_step_still_advances_its_learning_rate_schedule():
    w, optimizer = _sqrt_members([0.0])
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: step + 1)
    loss = w.sum().sqrt()
    skipped, _ = guarded_agent_step(optimizer, loss, max_grad_norm=1.0, scheduler=schedule)
    assert skipped.item() == 1.0 and w.item() == 0.0
    assert schedule.last_epoch == 1 and optimizer.param_groups[0]["lr"] == 0.2


def _td3_with_a_broken_actor(patience_updates: int = 12, compiled: bool = False):
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.hidden_sizes=[16,16]",
                       "algo.learning_starts=8", "algo.batch_size=8",
                       f"algo.compile={compiled}"])  # fmt: skip
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
    real_actor_loss = agent.actor_loss

    def nan_actor_loss(obs):  # a fault in the actor's step alone; the critic's is sound
        return real_actor_loss(obs) * float("nan")

    agent.actor_loss = nan_actor_loss
    return agent, [agent.update() for _ in range(patience_updates)]


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
def test_an_actor_skipped_again_and_again_counts_toward_divergence(compiled):
    """The same counts eager and with the whole update compiled (``compile=true`` on the CPU),
    and the actor's weights never move."""
    agent, metrics = _td3_with_a_broken_actor(compiled=compiled)
    assert agent.policy_delay == 2
    critic = [m["loss/critic"].item() for m in metrics]
    assert all(np.isfinite(critic))  # the critic learns on; only the actor's steps are skipped
    # from the first actor step (update 2) on, every update counts: nothing proves it recovered
    in_a_row = [m[SKIPPED_IN_A_ROW].item() for m in metrics]
    assert in_a_row == [0.0] + [float(i) for i in range(1, len(metrics))]
    assert metrics[-1][SKIPPED].item() == len(metrics) - 1
    # the actor never moved: its target, a copy moved toward it, is still equal to it
    actor, target = agent.actor.parameters(), agent.actor_target.parameters()
    assert all(torch.equal(p, q) for p, q in zip(actor, target, strict=True))
    restored = agent.guard.state_dict()
    agent.guard.load_state_dict({k: [0.0] for k in restored})
    agent.guard.load_state_dict(restored)  # the delayed step's verdict survives a checkpoint
    assert agent.update()[SKIPPED_IN_A_ROW].item() == len(metrics)


# --- PPO, DT and REINFORCE: a real update fed a NaN is skipped, the next one steps -------------
NAN = float("nan")


def _weights(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    return [p.detach().clone() for group in optimizer.param_groups for p in group["params"]]


def _learning_state(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    """Copies of the weights ``optimizer`` steps and of its Adam moments and step counts."""
    moments = [v.clone() for state in optimizer.state.values() for v in state.values()]
    return _weights(optimizer) + moments


def _same(before: list[torch.Tensor], after: list[torch.Tensor]) -> bool:
    return len(before) == len(after) and all(map(torch.equal, before, after))


def _skips_the_nan_update_then_steps(optimizers: list, update) -> None:
    """``update(NAN)`` after a finite ``update(None)``: the weights and Adam state of every one
    of ``optimizers`` untouched, the update counted in ``health/*``; the finite update after it
    steps every optimizer and ends the run of skips."""
    update(None)  # Adam's moments exist from here on
    before = [_learning_state(o) for o in optimizers]
    weights_before = [_weights(o) for o in optimizers]
    metrics = update(NAN)
    skipped = metrics[SKIPPED].item()
    assert skipped >= 1 and metrics[SKIPPED_IN_A_ROW].item() == skipped
    assert all(_same(b, _learning_state(o)) for b, o in zip(before, optimizers, strict=True))
    metrics = update(None)
    assert metrics[SKIPPED].item() == skipped and metrics[SKIPPED_IN_A_ROW].item() == 0
    for optimizer, old in zip(optimizers, weights_before, strict=True):
        weights = _weights(optimizer)
        assert all(torch.isfinite(w).all() for w in weights) and not _same(old, weights)


def _online_updates(agent, steps: int = 20):
    """``update(reward)``: Pendulum steps (every reward ``reward``, or the env's when None), from
    where the last call stopped, until ``agent`` updates; its metrics."""
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": steps})
    obs = [env.reset(seed=0)[0]]

    def update(reward: float | None) -> dict:
        while True:
            action = agent.act(obs[0], explore=True)
            next_obs, env_reward, term, trunc, _ = env.step(action)
            seen = env_reward if reward is None else reward
            agent.observe(Transition(obs[0], action, float(seen), next_obs, term, trunc))
            obs[0] = next_obs if not (term or trunc) else env.reset()[0]
            if metrics := agent.update():
                return metrics

    return update


def test_ppo_skips_every_minibatch_step_of_a_nan_rollout_and_learns_after_it():
    small = defaults_for(
        PPO, n_steps=16, n_minibatches=2, n_epochs=1, hidden_sizes=[8], normalize_reward=False
    )
    agent = PPO(3, [-2.0], [2.0], **small)
    _skips_the_nan_update_then_steps([agent.optimizer], _online_updates(agent))
    assert agent.guard.skipped.item() == 2  # both minibatch steps of the NaN rollout


def test_reinforce_skips_a_nan_update_of_its_policy_and_its_baseline():
    small = defaults_for(Reinforce, episodes_per_update=1, hidden_sizes=[8], baseline=True)
    agent = Reinforce(3, [-2.0], [2.0], **small)
    optimizers = [agent.optimizer, agent.value_optimizer]
    _skips_the_nan_update_then_steps(optimizers, _online_updates(agent))
    assert agent.guard.skipped.item() == 1  # one update, counted once for its two steps


def test_a_decision_transformer_skips_a_nan_batch_and_learns_after_it():
    small = defaults_for(
        DecisionTransformer,
        context_length=4,
        embed_dim=8,
        n_layers=1,
        dropout=0.0,
        batch_size=4,
        warmup_steps=10,
        max_episode_steps=50,
    )
    agent = DecisionTransformer(3, [-2.0], [2.0], dataset=tiny_offline_data(), **small)
    sample = agent.sampler.sample

    def update(poison: float | None) -> dict:
        """One update; with ``poison``, on a batch whose returns-to-go are multiplied by it."""
        if poison is not None:
            batch = sample(small["batch_size"])
            agent.sampler.sample = lambda n: batch._replace(
                returns_to_go=batch.returns_to_go * poison
            )
        try:
            return agent.update()
        finally:
            agent.sampler.sample = sample

    _skips_the_nan_update_then_steps([agent.optimizer], update)
    assert agent.scheduler.last_epoch == 3  # the warm-up counts the skipped update too


def test_a_checkpoint_keeps_the_cpu_generator_and_a_slot_for_cuda(store):
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.hidden_sizes=[16,16]",
                       "algo.learning_starts=100", *TINY, *store["overrides"]])  # fmt: skip
    train(cfg)
    (last,) = (store["path"] / "work").glob("runs/*/checkpoints/last.pt")
    state = read_checkpoint(last)
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
