"""TD3's critic target and actor loss against numbers worked out by hand.

Small hand-made batches, no env, no training loop. The networks are set by hand so that every
value is a known function: a critic ``Q(s, a) = c + w a`` (one hidden ReLU unit ``a + M``, on
for every action used here, and the output layer undoing the offset), an actor
``pi(s) = scale * sign * tanh(s) + bias`` (one hidden ReLU unit ``s + M``). With obs and
actions one-dimensional, the numbers below are the paper's formulas (Fujimoto et al. 2018,
Algorithm 1) evaluated on paper:

    a~ = clip(pi'(s') + clip(policy_noise * eps, -c, c) * half_range, low, high)
    y  = r + gamma (1 - terminated) min(Q'_1(s', a~), Q'_2(s', a~))
    critic loss = sum_i mean_n (y_n - Q_i(s_n, a_n))^2,   actor loss = -mean_n Q_1(s_n, pi(s_n))

y is read out of ``critic_loss`` itself: for one transition alone, with both online critics the
constant q, the loss is L(q) = 2 (y - q)^2, so L(0) - L(1) = 4y - 2 gives y linearly (sign
included), without reaching into the module for an intermediate.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from walkers.agents.base import Transition
from walkers.agents.factory import defaults_for
from walkers.agents.td3 import TD3
from walkers.data.replay import Batch

GAMMA = 0.5  # dyadic, and far from the default 0.99, so a wrong discount shows
M_ACTION = 8.0  # the critics' hidden offset: a + M > 0 for every action used here
M_OBS = 32.0  # the actors' hidden offset: s + M > 0 for every observation used here
SATURATED = 20.0  # tanh(20) == 1.0 in float32: pi(+-20) is exactly the bound


def make_td3(population: int = 1, low=(-2.0,), high=(2.0,), **overrides) -> TD3:
    hp = defaults_for(
        TD3,
        hidden_sizes=[4],
        batch_size=4,
        learning_starts=0,
        buffer_size=64,
        gamma=GAMMA,
        **overrides,
    )
    return TD3(1, list(low), list(high), **hp, population=population, seed=0)


# --- networks set by hand ---------------------------------------------------------------------
@torch.no_grad()
def set_q(critic, j: int, c: float, w: float) -> None:
    """Ensemble member ``j`` of an MLP critic (obs 1, action 1, one hidden layer) becomes
    Q_j(s, a) = c + w a, for a > -M_ACTION: hidden unit 0 = relu(a + M), the others 0, and
    out = w * unit0 + (c - w M)."""
    (hidden,) = critic.hidden
    hidden.weight[j].zero_()
    hidden.bias[j].zero_()
    hidden.weight[j, 1, 0] = 1.0  # input order is [s, a]
    hidden.bias[j, 0, 0] = M_ACTION
    critic.out.weight[j].zero_()
    critic.out.weight[j, 0, 0] = w
    critic.out.bias[j, 0, 0] = c - w * M_ACTION


@torch.no_grad()
def set_actor(actor, j: int, sign: float = 1.0) -> None:
    """Ensemble member ``j`` of an actor (obs 1, action 1, one hidden layer) becomes
    pi_j(s) = tanh(sign * s) * action_scale + action_bias, for s > -M_OBS."""
    first, last = actor.layers
    first.weight[j].zero_()
    first.bias[j].zero_()
    first.weight[j, 0, 0] = 1.0
    first.bias[j, 0, 0] = M_OBS
    last.weight[j].zero_()
    last.weight[j, 0, 0] = sign
    last.bias[j, 0, 0] = -sign * M_OBS


def batch(obs, action, reward, next_obs, terminated) -> Batch:
    """A Batch from nested lists shaped (K, N): obs/action/next_obs get their feature dim."""

    def t(x):
        return torch.tensor(x, dtype=torch.float32)

    return Batch(
        t(obs)[..., None], t(action)[..., None], t(reward), t(next_obs)[..., None], t(terminated)
    )


def targets(agent: TD3, b: Batch, noise: torch.Tensor | None) -> torch.Tensor:
    """y ``(K, N)`` read out of ``critic_loss``, one transition at a time (see the module
    docstring). Overwrites the online critics."""
    K, N = b.reward.shape
    ys = torch.empty(K, N)
    for n in range(N):
        one = Batch(*(field[:, n : n + 1] for field in b[:5]))
        eps = None if noise is None else noise[:, n : n + 1]
        losses = []
        for q in (0.0, 1.0):
            for j in range(agent.critic.out.weight.shape[0]):
                set_q(agent.critic, j, c=q, w=0.0)
            loss, q_mean = agent.critic_loss(one, eps)
            assert loss.shape == (K,) and q_mean.shape == (K,)
            torch.testing.assert_close(q_mean, torch.full((K,), q))
            losses.append(loss.detach())
        ys[:, n] = (losses[0] - losses[1] + 2.0) / 4.0
    return ys


def zeros_noise(b: Batch) -> torch.Tensor:
    return torch.zeros_like(b.action)


def close(actual, expected, atol=1e-5):
    torch.testing.assert_close(
        torch.as_tensor(actual, dtype=torch.float32),
        torch.as_tensor(expected, dtype=torch.float32),
        rtol=0,
        atol=atol,
    )


# --- the hand-set networks are what they say ----------------------------------------------------
def test_hand_set_networks_compute_the_stated_functions():
    agent = make_td3()
    set_q(agent.critic, 0, c=3.0, w=1.0)
    set_q(agent.critic, 1, c=5.0, w=-1.0)
    set_actor(agent.actor, 0)
    s = torch.tensor([[[0.0], [0.5], [SATURATED], [-SATURATED]]])
    a = torch.tensor([[[-2.0], [0.0], [1.5], [2.0]]])
    close(agent.q_values(agent.critic, s, a), [[[1.0, 3.0, 4.5, 5.0], [7.0, 5.0, 3.5, 3.0]]])
    close(agent.actor(s)[0, :, 0], [0.0, 2 * math.tanh(0.5), 2.0, -2.0], atol=1e-6)
    assert agent.actor(s)[0, 2, 0].item() == 2.0  # saturated: exactly the bound


# --- 1. terminated vs truncated -------------------------------------------------------------
def test_terminated_target_is_the_reward_truncated_bootstraps():
    """Two identical transitions, one ended by the MDP (terminated) and one by a time limit
    (truncated): the replay stores terminated only, and only the terminated one's target drops
    the bootstrap. Q'_1 = 3 + a, Q'_2 = 5 - a, pi'(s') = 2 tanh(s'), s' = 20: a~ = 2 (no
    noise), min(5, 3) = 3, y = 1.5 + 0.5 * 3 = 3.0 truncated, 1.5 terminated."""
    agent = make_td3()
    set_q(agent.critic_target, 0, c=3.0, w=1.0)
    set_q(agent.critic_target, 1, c=5.0, w=-1.0)
    set_actor(agent.actor_target, 0)
    same = ([0.5], [1.0], 1.5, [SATURATED])
    agent.observe(Transition(*same, terminated=True, truncated=False))
    agent.observe(Transition(*same, terminated=False, truncated=True))
    buf = agent.buffer
    assert buf.terminated[0, :2].tolist() == [1.0, 0.0]
    b = Batch(*(getattr(buf, f)[:, :2] for f in Batch._fields[:5]))
    assert b.reward.shape == (1, 2) and b.obs.shape == (1, 2, 1)

    y = targets(agent, b, zeros_noise(b))
    close(y, [[1.5, 3.0]])
    # the same through the update's own path: no smoothing noise given at all
    close(targets(agent, b, None), [[1.5, 3.0]])

    # the batch's loss as a whole: sum over the critics of the mean over N (Q_1 = 0, Q_2 = 1)
    set_q(agent.critic, 0, c=0.0, w=0.0)
    set_q(agent.critic, 1, c=1.0, w=0.0)
    loss, q_mean = agent.critic_loss(b, zeros_noise(b))
    close(loss, [(1.5**2 + 3.0**2) / 2 + (0.5**2 + 2.0**2) / 2])
    close(q_mean, [0.5])


def test_terminated_target_ignores_huge_next_values():
    """terminated = 1 multiplies the bootstrap away entirely, however large Q' is (kept to
    float32-friendly sizes: y is read out of a squared error)."""
    agent = make_td3()
    set_q(agent.critic_target, 0, c=64.0, w=0.0)
    set_q(agent.critic_target, 1, c=128.0, w=0.0)
    b = batch([[0.0, 0.0]], [[0.0, 0.0]], [[-0.75, -0.75]], [[0.0, 0.0]], [[1.0, 0.0]])
    close(targets(agent, b, zeros_noise(b)), [[-0.75, -0.75 + GAMMA * 64.0]])


# --- 2. target policy smoothing: the clamps ---------------------------------------------------
# (pi'(s') via s', eps, a~ by hand); policy_noise 0.2, noise_clip 0.5, in half-ranges (2 here)
SMOOTHING_SYMMETRIC = [
    (0.0, 1.0, 0.4),  # 0.2 * 1 = 0.2 < 0.5 passes: 0 + 0.2 * 2
    (0.0, -2.0, -0.8),  # -0.4 passes: 0 - 0.4 * 2
    (0.0, 10.0, 1.0),  # 2.0 clipped to 0.5: 0 + 0.5 * 2
    (0.0, -10.0, -1.0),  # -2.0 clipped to -0.5
    (SATURATED, 10.0, 2.0),  # 2 + 1 = 3, clamped to the upper bound 2
    (SATURATED, -10.0, 1.0),  # 2 - 1
    (-SATURATED, 1.0, -1.6),  # -2 + 0.4, in bounds
    (-SATURATED, -1.0, -2.0),  # -2 - 0.4 = -2.4, clamped to the lower bound -2
]
# bounds [-1, 3]: half-range 2, centre 1, so pi'(s') = 2 tanh(s') + 1
SMOOTHING_SHIFTED = [
    (0.0, 1.0, 1.4),  # 1 + 0.2 * 2
    (0.0, 10.0, 2.0),  # 1 + 0.5 * 2
    (0.0, -10.0, 0.0),  # 1 - 0.5 * 2
    (SATURATED, 10.0, 3.0),  # 3 + 1, clamped to 3
    (SATURATED, -1.0, 2.6),  # 3 - 0.4
    (-SATURATED, -1.0, -1.0),  # -1 - 0.4, clamped to -1
    (-SATURATED, 10.0, 0.0),  # -1 + 1
]


@pytest.mark.parametrize(
    ("low", "high", "rows"),
    [(-2.0, 2.0, SMOOTHING_SYMMETRIC), (-1.0, 3.0, SMOOTHING_SHIFTED)],
    ids=["bounds[-2,2]", "bounds[-1,3]"],
)
def test_smoothing_noise_is_clipped_in_half_ranges_and_the_action_to_the_bounds(low, high, rows):
    """Q'_1 = Q'_2 = a and r = 0, so y = gamma * a~: the target action, read out of the loss."""
    agent = make_td3(low=(low,), high=(high,), policy_noise=0.2, noise_clip=0.5)
    set_q(agent.critic_target, 0, c=0.0, w=1.0)
    set_q(agent.critic_target, 1, c=0.0, w=1.0)
    set_actor(agent.actor_target, 0)
    next_obs, eps, expected = (list(col) for col in zip(*rows, strict=True))
    n = len(rows)
    b = batch([[0.0] * n], [[0.0] * n], [[0.0] * n], [next_obs], [[0.0] * n])
    noise = torch.tensor(eps, dtype=torch.float32).view(1, n, 1)
    close(targets(agent, b, noise) / GAMMA, [expected])


def test_the_update_draws_one_standard_normal_shaped_like_the_actions_and_none_without_smoothing():
    for policy_noise, draws in ((0.2, 1), (0.0, 0)):
        agent = make_td3(population=2, policy_noise=policy_noise)
        for _ in range(4):
            agent.observe_population([Transition([0.5], [0.0], 1.0, [0.5], False, False)] * 2)
        shapes = []
        agent.noise_like = lambda x, shapes=shapes: shapes.append(x.shape) or torch.randn_like(x)
        assert agent.update()
        assert shapes == [(2, 4, 1)] * draws


# --- 3. the min of the twins --------------------------------------------------------------------
def member0_setup(agent: TD3) -> Batch:
    """Member 0: Q'_1 = 2 + a, Q'_2 = 1 - a, pi'(s') = 2 tanh(s'); s' = 20, 0, -20 give
    a~ = 2, 0, -2, so (Q'_1, Q'_2) = (4, -1), (2, 1), (0, 3): the min is Q'_2, Q'_2, Q'_1;
    r = 1: y = 1 + 0.5 * (-1, 1, 0) = (0.5, 1.5, 1.0)."""
    set_q(agent.critic_target, 0, c=2.0, w=1.0)
    set_q(agent.critic_target, 1, c=1.0, w=-1.0)
    set_actor(agent.actor_target, 0)
    return batch([[0.0] * 3], [[0.0] * 3], [[1.0] * 3], [[SATURATED, 0.0, -SATURATED]], [[0.0] * 3])


MEMBER0_Y = [0.5, 1.5, 1.0]


def test_target_takes_the_smaller_twin_per_sample():
    agent = make_td3()
    b = member0_setup(agent)
    close(targets(agent, b, zeros_noise(b)), [MEMBER0_Y])


def test_population_of_two_members_are_independent():
    """Member 1 has its own target actor (pi'(s') = -2 tanh(s')), own twins (Q'_1 = -a,
    Q'_2 = 1 + a/2) and own batch: s' = -20, 20, 0 give a~ = 2, -2, 0, (Q'_1, Q'_2) =
    (-2, 2), (2, 0), (0, 1): the min is Q'_1, Q'_2, Q'_1; r = 0.5, the last terminated:
    y = 0.5 + 0.5 * (-2, 0, .) = (-0.5, 0.5, 0.5). Member 0's numbers are the single agent's."""
    agent = make_td3(population=2)
    b0 = member0_setup(agent)
    # member k's twins are critics 2k and 2k + 1; its actor is actor member k
    set_q(agent.critic_target, 2, c=0.0, w=-1.0)
    set_q(agent.critic_target, 3, c=1.0, w=0.5)
    set_actor(agent.actor_target, 1, sign=-1.0)
    b1 = batch(
        [[0.0] * 3], [[0.0] * 3], [[0.5] * 3], [[-SATURATED, SATURATED, 0.0]], [[0.0, 0.0, 1.0]]
    )
    b = Batch(*(torch.cat([f0, f1]) for f0, f1 in zip(b0[:5], b1[:5], strict=True)))
    y = targets(agent, b, zeros_noise(b))
    close(y, [MEMBER0_Y, [-0.5, 0.5, 0.5]])

    # member 0's loss does not move when member 1's networks and batch do, and vice versa
    set_q(agent.critic, 0, c=0.25, w=0.5)
    set_q(agent.critic, 1, c=-0.5, w=0.0)
    set_q(agent.critic, 2, c=0.0, w=0.0)
    set_q(agent.critic, 3, c=0.0, w=0.0)
    before, _ = agent.critic_loss(b, zeros_noise(b))
    set_q(agent.critic_target, 3, c=-7.0, w=0.0)  # member 1's Q'_2 now always the min
    set_actor(agent.actor_target, 1, sign=1.0)
    set_q(agent.critic, 3, c=2.0, w=1.0)
    b_changed = b._replace(reward=b.reward.clone().index_fill_(0, torch.tensor([1]), 9.0))
    after, _ = agent.critic_loss(b_changed, zeros_noise(b))
    assert after[0].item() == before[0].item()
    assert after[1].item() != before[1].item()
    # and member 0's loss by hand: Q_1(s, 0) = 0.25, Q_2 = -0.5 against y = (0.5, 1.5, 1.0)
    y0 = torch.tensor(MEMBER0_Y)
    close(before[0], ((y0 - 0.25) ** 2).mean() + ((y0 + 0.5) ** 2).mean())


# --- 4. the actor loss reads Q_1 only -----------------------------------------------------------
@pytest.mark.parametrize("population", [1, 2])
def test_actor_loss_is_minus_mean_q1_and_ignores_q2(population):
    """pi(s) = 2 tanh(s); Q_1 = 1 + a/2, so -mean Q_1(s, pi(s)) = -(1 + mean tanh(s)), and its
    gradient in the actor's output bias (the pre-tanh z = s) is -(1/N) sum 0.5 * 2 (1 - tanh^2)."""
    agent = make_td3(population=population)
    s = [0.0, 0.5, -1.0]
    obs = torch.tensor([s] * population).unsqueeze(-1)
    for k in range(population):
        set_actor(agent.actor, k)
        set_q(agent.critic, 2 * k, c=1.0, w=0.5)
        set_q(agent.critic, 2 * k + 1, c=-3.0, w=2.0)

    def loss_and_grad():
        agent.actor.zero_grad(set_to_none=True)
        loss = agent.actor_loss(Batch(obs, *[None] * 4))  # it reads the states alone
        loss.sum().backward()
        return loss.detach(), agent.actor.layers[-1].bias.grad[:, 0, 0].clone()

    loss, grad = loss_and_grad()
    assert loss.shape == (population,)
    expected_loss = -(1.0 + np.mean(np.tanh(s)))
    expected_grad = -np.mean(0.5 * 2.0 * (1.0 - np.tanh(s) ** 2))
    close(loss, [expected_loss] * population, atol=1e-6)
    close(grad, [expected_grad] * population, atol=1e-6)

    # critic 2 (every member's) changed: the same loss and gradient, bit for bit
    for k in range(population):
        set_q(agent.critic, 2 * k + 1, c=100.0, w=-5.0)
    loss2, grad2 = loss_and_grad()
    assert torch.equal(loss2, loss) and torch.equal(grad2, grad)

    # the last member's critic 1 changed to Q_1 = 1 - a/4: its loss and gradient move, by hand;
    # any other member's do not
    last = population - 1
    set_q(agent.critic, 2 * last, c=1.0, w=-0.25)
    loss3, grad3 = loss_and_grad()
    close(loss3[last], -(1.0 - 0.5 * np.mean(np.tanh(s))), atol=1e-6)
    close(grad3[last], -np.mean(-0.25 * 2.0 * (1.0 - np.tanh(s) ** 2)), atol=1e-6)
    assert torch.equal(loss3[:last], loss[:last]) and torch.equal(grad3[:last], grad[:last])


# --- 5. the delayed policy update ---------------------------------------------------------------
def snapshot(module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def same(module, snap) -> bool:
    return all(torch.equal(p, q) for p, q in zip(module.parameters(), snap, strict=True))


@pytest.mark.parametrize("population", [1, 2])
def test_policy_delay_steps_actor_and_targets_every_second_update(population):
    tau = 0.25  # not 0.5: tau and 1 - tau swapped would show
    agent = make_td3(population=population, policy_delay=2, tau=tau, lr=1e-2)
    rng = np.random.default_rng(0)
    for _ in range(8):
        agent.observe_population(
            [
                Transition(
                    rng.normal(size=1),
                    rng.uniform(-2, 2, size=1),
                    float(rng.normal()),
                    rng.normal(size=1),
                    terminated=False,
                    truncated=False,
                )
                for _ in range(population)
            ]
        )
    actor0, critic0 = snapshot(agent.actor), snapshot(agent.critic)
    actor_t0, critic_t0 = snapshot(agent.actor_target), snapshot(agent.critic_target)
    assert all(torch.equal(p, q) for p, q in zip(critic_t0, critic0, strict=True))

    m1 = agent.update()  # num_updates 1: the critics only
    assert agent.num_updates == 1 and "loss/critic" in m1 and "loss/actor" not in m1
    assert not same(agent.critic, critic0)
    assert same(agent.actor, actor0)
    assert same(agent.actor_target, actor_t0) and same(agent.critic_target, critic_t0)

    m2 = agent.update()  # num_updates 2: critics, then the actor, then both targets
    assert agent.num_updates == 2 and "loss/actor" in m2
    assert m2["loss/actor"].shape == (population,)
    assert not same(agent.actor, actor0)
    critic2, actor2 = snapshot(agent.critic), snapshot(agent.actor)
    for target, old, new in [
        (agent.critic_target, critic_t0, critic2),
        (agent.actor_target, actor_t0, actor2),
    ]:
        for p, p_old, p_new in zip(target.parameters(), old, new, strict=True):
            close(p, (1 - tau) * p_old + tau * p_new, atol=1e-7)
            assert not torch.equal(p, p_old)
    # one parameter spelled out: the critics' output bias, every member's every twin
    b_old, b_new = critic_t0[-1].flatten().tolist(), critic2[-1].flatten().tolist()
    for got, o, n in zip(
        agent.critic_target.out.bias.flatten().tolist(), b_old, b_new, strict=True
    ):
        assert got == pytest.approx(0.75 * o + 0.25 * n, abs=1e-7)

    actor_t2, critic_t2 = snapshot(agent.actor_target), snapshot(agent.critic_target)
    m3 = agent.update()  # num_updates 3: the critics only again
    assert "loss/actor" not in m3
    assert same(agent.actor, actor2) and not same(agent.critic, critic2)
    assert same(agent.actor_target, actor_t2) and same(agent.critic_target, critic_t2)
