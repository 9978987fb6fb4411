"""Parity with Stable-Baselines3 (2.9.2) and sb3-contrib (2.9.2), proven update by update, for
TD3, DDPG, SAC, CrossQ and PPO.

Each test builds walkers' agent and SB3's model from the same walkers hyperparameters (SB3's
through the impl=sb3 mapping, :class:`walkers.agents.sb3.twin.SB3Twin`), with 32-32 networks on a
made-up space (obs 3, actions 2 in [-1, 1]: SB3 acts in [-1, 1], so with these bounds both sides
feed their critics the same numbers); copies SB3's weights into walkers' (SB3's targets perturbed
first, so no target equals its online net; CrossQ's renormalization statistics set as in a run in
progress); feeds both the same data and the same random numbers; runs the update(s) and compares
every weight, target, temperature, running statistic and Adam moment (exp_avg, exp_avg_sq, step):

- off-policy: ``agent.sample`` and ``model.replay_buffer.sample`` return the same batch; SB3
  draws its own noise (TD3: one ``Tensor.normal_`` for the target smoothing; SAC: two
  ``Normal.rsample``, first eps for a ~ pi(.|s), then for a' ~ pi(.|s'); CrossQ: first for
  a' ~ pi(.|s'), then, on the delayed steps only, for a ~ pi(.|s)), which the test records and
  hands to walkers through ``agent.noise_like``, in the order the update draws;
- PPO: one rollout (a termination, a time-limit truncation and an unfinished tail) written into
  SB3's RolloutBuffer as its collect_rollouts would and into walkers' Rollout; SB3's minibatch
  permutations (``np.random.permutation`` in ``RolloutBuffer.get``) are walkers' own.

Gaps: weights and running statistics as max abs difference; moments as max abs difference over
the largest magnitude of the tensor (moments range from 1e-12 to 1); Adam step counts and
renormalization pass counts exactly. Proven:

- TD3 (critic-only updates and actor updates, 4 updates), DDPG (2), PPO without value clipping
  (3 epochs x 4 minibatches): equal to float32 rounding (WEIGHT_ATOL, MOMENT_RTOL).
- SAC (3 updates): alpha equal to rounding, so the order of the temperature step (SB3 steps it
  before the critics, walkers after the actor) changes nothing: both use the alpha from before
  the update in the critic target and the actor loss. Both critic losses are 1/2 sum MSE. One
  real difference, SB3's choice, shown to be the whole gap by undoing it on SB3's side: SB3's
  log pi subtracts log(1 - tanh(u)^2 + 1e-6), walkers' the exact log(1 - tanh(u)^2): actor
  moments ~1e-4 apart; with SB3's epsilon set to 0 SAC agrees to float32 rounding.
- CrossQ (sb3-contrib's, 6 updates: critic-only and delayed actor and temperature steps, the
  renormalizations in their warm-up and past it): with SB3's log epsilon undone, equal to
  float64 rounding (F64_WEIGHT_ATOL, F64_MOMENT_RTOL; compared in float64, as that constant's
  comment explains); the epsilon left in, a gap of SAC's size.
- PPO with value clipping (walkers: ppo2's max((V-R)^2, (clip(V)-R)^2), SB3: clipped V): the
  policy and its moments agree, the value net does not; with SB3's form put in place of walkers'
  ``value_loss`` everything agrees again, so that function is the one difference.
- Each twin has a test changing one reward on SB3's side only: the weights then part, so the
  comparisons are not vacuous.

A feature constant over the batch (a ReLU unit off for the whole batch) gets a finite gradient
in the renormalization's warm-up on both sides (test_crossq_renormalization_gradient_for_a_
constant_...; walkers once picked its branch so that the unpicked one's gradient was NaN).
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

from walkers.agents.base import Transition
from walkers.agents.common.networks import EnsembleLinear
from walkers.agents.crossq import CrossQ
from walkers.agents.ddpg import DDPG
from walkers.agents.factory import defaults_for
from walkers.agents.ppo import PPO
from walkers.agents.sac import SAC
from walkers.agents.td3 import TD3
from walkers.data.replay import Batch

pytest.importorskip("stable_baselines3")
from stable_baselines3.common import policies as sb3_policies  # noqa: E402
from stable_baselines3.common.type_aliases import ReplayBufferSamples  # noqa: E402

from walkers.agents.sb3.twin import SB3Twin  # noqa: E402

OBS_DIM, ACT_DIM, BATCH, HIDDEN = 3, 2, 32, [32, 32]
LOW, HIGH = [-1.0] * ACT_DIM, [1.0] * ACT_DIM

#: Tolerances. Measured on this machine (max over every group and update of these tests): weights
#: 8.9e-8 (float32 rounding: fused vs for-loop Adam, lerp vs mul-add Polyak, summation order);
#: moments 1.7e-6 (SAC with SB3's log epsilon undone), 1.0e-6 (PPO), 4.4e-7 (TD3, DDPG).
WEIGHT_ATOL = 1e-6
MOMENT_RTOL = 1e-5
#: SB3's log epsilon left in, measured: SAC (float32): actor weights 7.7e-7, critics 1.2e-7;
#: moments 8.3e-5 (actor), 1.0e-5 (critics), 3.8e-6 (alpha). CrossQ (float64): weights 7.4e-7;
#: moments 7.8e-5 (actor), 2.1e-5 (critics), 7.8e-6 (alpha). (The epsilon enters the actor's
#: loss, the temperature's and the critics' target.)
SAC_WEIGHT_ATOL = 1e-4
SAC_MOMENT_RTOL = 1e-3
#: CrossQ in float64, SB3's log epsilon undone, measured: weights 1.4e-12, running statistics
#: 1.3e-13; moments 2.5e-12 (actor), 2.4e-13 (critics), 5e-15 (alpha); at most 1.5e-12 with
#: five other seeds of the batches. Why float64: in float32 a hidden Linear's bias whose ReLU is
#: on for every sample of the batch has a gradient that is 0 but for rounding (the next
#: renormalization subtracts the batch mean, bias included): ~2e-8 on both sides, 20% apart.
#: Adam's first step, lr g / (|g| + 1e-8), makes that 0.63 lr on one side and 0.67 lr on the
#: other: 4.6e-5 apart (3e-4 with other batches), and the actor's later passes carry it on
#: (moments up to 1.5e-3). In float64 the same rounding leaves gaps of ~1e-12.
F64_WEIGHT_ATOL = 1e-10
F64_MOMENT_RTOL = 1e-10
#: A gap no rounding explains, which the non-vacuity tests require (they measure >= 1e-3 weights).
CLEARLY_DIFFERENT = 1e-4

#: (group, walkers tensor, its SB3 tensor or per member the SB3 tensors it stacks)
Pair = tuple[str, torch.Tensor, object]


class TinyEnv(gym.Env):
    """A space for SB3 to build its model on; the tests never step it."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
    action_space = gym.spaces.Box(np.float32(-1), np.float32(1), (ACT_DIM,), np.float32)

    def reset(self, *, seed=None, options=None):
        return np.zeros(OBS_DIM, np.float32), {}

    def step(self, action):
        return np.zeros(OBS_DIM, np.float32), 0.0, False, False, {}


@pytest.fixture(autouse=True)
def _keep_global_rngs():
    """SB3 seeds the global torch/numpy/random streams: give them back as found."""
    states = torch.get_rng_state(), np.random.get_state(), random.getstate()
    yield
    torch.set_rng_state(states[0])
    np.random.set_state(states[1])
    random.setstate(states[2])


# --- building both sides -------------------------------------------------------------------------
def build(agent_class: type, algo: str, **overrides):
    """walkers' agent and SB3's model from the same walkers hyperparameters."""
    hp = defaults_for(agent_class, hidden_sizes=HIDDEN, **overrides)
    twin = SB3Twin(algo, hp, OBS_DIM, LOW, HIGH, seed=0, device="cpu")
    twin.attach(TinyEnv(), total_steps=1000)
    return agent_class(OBS_DIM, LOW, HIGH, **hp, seed=0), twin.model


#: the replay-based algorithms' settings here (tau: of those with targets)
OFF_POLICY = {"batch_size": BATCH, "learning_starts": 0, "buffer_size": 1000, "lr": 1e-3}


def off_policy(agent_class: type, algo: str, **overrides):
    return build(agent_class, algo, **OFF_POLICY, tau=0.05, **overrides)


# --- which walkers tensor is which SB3 tensor --------------------------------------------------
def linears(module: nn.Module) -> list[nn.Linear]:
    return [m for m in module.modules() if isinstance(m, nn.Linear)]


def ensemble_pairs(group: str, ours: EnsembleLinear, members: list[list[nn.Linear]]) -> list:
    """Walkers' ensemble layer and, per member, the SB3 layer(s) whose outputs it stacks (one,
    or SAC's mean and log-std heads, which walkers' actor computes as one layer)."""
    return [
        (group, ours.weight, [[lin.weight for lin in m] for m in members]),
        (group, ours.bias, [[lin.bias for lin in m] for m in members]),
    ]


def as_ours(theirs, get: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """SB3's tensor(s) (or their Adam moments, via ``get``) in walkers' layout: an ensemble
    Linear's weight is (members, in, out) = W.T stacked, its bias (members, 1, out); an ensemble
    renormalization's vectors (members, 1, features), its step counts (members,)."""
    if isinstance(theirs, torch.Tensor):  # same layout on both sides
        return get(theirs)
    if all(p.dim() == 0 for pieces in theirs for p in pieces):  # one number per member
        return torch.stack([get(p) for (p,) in theirs])
    members = [torch.cat([get(p) for p in pieces]) for pieces in theirs]
    return torch.stack([m.T if m.dim() == 2 else m[None] for m in members])


def deterministic_pairs(agent, model) -> list[Pair]:
    """TD3/DDPG: actor, actor target, the critics (members of one ensemble) and their targets."""
    pairs = []
    for group, ours, theirs in [
        ("actor", agent.actor, model.actor),
        ("actor_target", agent.actor_target, model.actor_target),
    ]:
        for o, t in zip(ours.layers, linears(theirs), strict=True):
            pairs += ensemble_pairs(group, o, [[t]])
    return pairs + critic_pairs(agent, model)


def critic_pairs(agent, model) -> list[Pair]:
    pairs = []
    for group, ours, theirs in [
        ("critic", agent.critic, model.critic),
        ("critic_target", agent.critic_target, model.critic_target),
    ]:
        qs = [linears(q) for q in theirs.q_networks]
        for i, o in enumerate([*ours.hidden, ours.out]):
            pairs += ensemble_pairs(group, o, [[q[i]] for q in qs])
    return pairs


def gaussian_actor_pairs(agent, model) -> list[Pair]:
    """SAC's and CrossQ's actor: SB3's hidden Linears, then its mean and log-std heads, which
    walkers' head computes as one layer."""
    heads = [
        *([lin] for lin in linears(model.actor.latent_pi)),
        [model.actor.mu, model.actor.log_std],
    ]
    pairs = []
    for o, t in zip(agent.actor.layers, heads, strict=True):
        pairs += ensemble_pairs("actor", o, [t])
    return pairs


def temperature_pair(agent, model) -> list[Pair]:
    return [("temperature", agent.temperature.log_alpha, model.log_ent_coef)]


def sac_pairs(agent, model) -> list[Pair]:
    return (
        gaussian_actor_pairs(agent, model)
        + critic_pairs(agent, model)
        + temperature_pair(agent, model)
    )


def renorms(module: nn.Module) -> list[nn.Module]:
    """sb3-contrib's Batch Renormalization layers in ``module``, in order."""
    from sb3_contrib.common.torch_layers import BatchRenorm

    return [m for m in module.modules() if isinstance(m, BatchRenorm)]


def renorm_pairs(group: str, ours, members: list[nn.Module]) -> list[Pair]:
    """Walkers' ensemble renormalization (an ``EnsembleBatchRenorm``) and, per member, the
    BatchRenorm1d it stacks: scale and bias (learned, Adam moments compared), running mean and
    variance (ra_mean, ra_var) and pass count."""
    return [
        (group, ours.scale, [[m.scale] for m in members]),
        (group, ours.bias, [[m.bias] for m in members]),
        (group, ours.running_mean, [[m.ra_mean] for m in members]),
        (group, ours.running_var, [[m.ra_var] for m in members]),
        (group, ours.steps, [[m.steps] for m in members]),
    ]


def crossq_pairs(agent, model) -> list[Pair]:
    """The actor (renormalizations before each Linear and before the heads), the critics
    (q_networks: BatchRenorm1d, Linear, ReLU, ..., BatchRenorm1d, Linear) and the temperature."""
    pairs = gaussian_actor_pairs(agent, model)
    for o, t in zip(agent.actor.norms, renorms(model.actor.latent_pi), strict=True):
        pairs += renorm_pairs("actor", o, [t])
    qs = model.critic.q_networks
    for i, o in enumerate(agent.critic.layers):
        pairs += ensemble_pairs("critic", o, [[linears(q)[i]] for q in qs])
    for i, o in enumerate(agent.critic.norms):
        pairs += renorm_pairs("critic", o, [renorms(q)[i] for q in qs])
    assert len(agent.critic.layers) == len(linears(qs[0]))
    assert len(agent.critic.norms) == len(renorms(qs[0]))
    return pairs + temperature_pair(agent, model)


def ppo_pairs(agent, model) -> list[Pair]:
    p = model.policy
    policy = linears(p.mlp_extractor.policy_net) + [p.action_net]
    value = linears(p.mlp_extractor.value_net) + [p.value_net]
    pairs = [("policy", agent.policy.log_std, p.log_std)]
    for group, ours, theirs in [
        ("policy", agent.policy.mean, policy),
        ("value", agent.value, value),
    ]:
        for o, t in zip(linears(ours), theirs, strict=True):
            pairs += [(group, o.weight, t.weight), (group, o.bias, t.bias)]
    return pairs


def walkers_optimizers(agent) -> list[torch.optim.Optimizer]:
    names = ("actor_optimizer", "critic_optimizer", "alpha_optimizer", "optimizer")
    return [getattr(agent, n) for n in names if hasattr(agent, n)]


def sb3_optimizers(model) -> list[torch.optim.Optimizer]:
    if hasattr(model, "rollout_buffer"):  # PPO: one optimizer for the policy and value nets
        return [model.policy.optimizer]
    found = [model.actor.optimizer, model.critic.optimizer]
    temperature = getattr(model, "ent_coef_optimizer", None)  # SAC
    return found + ([temperature] if temperature is not None else [])


def adam_states(optimizers: list[torch.optim.Optimizer]) -> dict[torch.Tensor, dict]:
    """Each parameter's Adam state (empty before its first step), whichever optimizer holds it."""
    return {p: o.state.get(p, {}) for o in optimizers for g in o.param_groups for p in g["params"]}


# --- copying and comparing ------------------------------------------------------------------------
@torch.no_grad()
def load_sb3_weights_into_walkers(pairs: list[Pair], model) -> None:
    """Perturb SB3's targets (so no target equals its online net), then copy every SB3 tensor
    into its walkers counterpart."""
    generator = torch.Generator().manual_seed(1)
    for name in ("actor_target", "critic_target"):
        for p in getattr(model, name).parameters() if hasattr(model, name) else []:
            p.add_(0.05 * torch.randn(p.shape, generator=generator))
    for _, ours, theirs in pairs:
        ours.copy_(as_ours(theirs, lambda p: p))


def kind_of(ours: torch.Tensor) -> str:
    """A weight (parameter), a running statistic (float buffer) or a pass count."""
    if isinstance(ours, nn.Parameter):
        return "weights"
    return "running" if ours.is_floating_point() else "passes"


def gaps(pairs: list[Pair], agent, model) -> dict:
    """Per group: ``weights`` max abs diff; ``exp_avg``/``exp_avg_sq`` max abs diff over the
    largest magnitude of the SB3 moment; ``step`` max abs diff; for CrossQ's renormalizations
    also ``running`` (running mean and variance) max abs diff and ``passes`` (their step
    counts) max abs diff."""
    ours_states = adam_states(walkers_optimizers(agent))
    theirs_states = adam_states(sb3_optimizers(model))
    out: dict[str, float] = {}

    def note(key: str, value: float) -> None:
        value = float("inf") if math.isnan(value) else value  # NaN on one side: no agreement
        out[key] = max(out.get(key, 0.0), value)

    for group, ours, theirs in pairs:
        note(f"{group}/{kind_of(ours)}", (ours - as_ours(theirs, lambda p: p)).abs().max().item())
        ours_state = ours_states.get(ours)
        if ours_state is None:  # a target or a buffer: no optimizer
            continue
        theirs_first = theirs if isinstance(theirs, torch.Tensor) else theirs[0][0]
        if bool(ours_state) != bool(theirs_states[theirs_first]):  # one side stepped, not the other
            note(f"{group}/step", float("inf"))
            continue
        if not ours_state:
            continue
        for moment in ("exp_avg", "exp_avg_sq"):
            want = as_ours(theirs, lambda p, m=moment: theirs_states[p][m])
            scale = want.abs().max().clamp_min(1e-30)
            note(f"{group}/{moment}", ((ours_state[moment] - want).abs().max() / scale).item())
        step = as_ours(theirs, lambda p: theirs_states[p]["step"].expand(p.shape))
        note(f"{group}/step", (ours_state["step"] - step).abs().max().item())
    return out


def assert_agree(found: dict, weight_atol=WEIGHT_ATOL, moment_rtol=MOMENT_RTOL) -> None:
    """Every gap within tolerance (running statistics: as weights); Adam's step counts and the
    renormalizations' pass counts equal."""
    limits = {
        "weights": weight_atol,
        "running": weight_atol,
        "exp_avg": moment_rtol,
        "exp_avg_sq": moment_rtol,
        "step": 0,
        "passes": 0,
    }
    too_far = {k: v for k, v in found.items() if not v <= limits[k.split("/")[1]]}
    assert not too_far, f"beyond tolerance: {too_far} (all gaps: {found})"


def differing(found: dict) -> set[str]:
    return {k for k, v in found.items() if v > CLEARLY_DIFFERENT}


# --- off-policy: one batch, SB3's noise recorded and handed to walkers ----------------------------
def make_batch(seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "obs": torch.randn(BATCH, OBS_DIM, generator=g),
        "action": torch.rand(BATCH, ACT_DIM, generator=g) * 2 - 1,
        "reward": torch.randn(BATCH, generator=g),
        "next_obs": torch.randn(BATCH, OBS_DIM, generator=g),
        "terminated": (torch.arange(BATCH) % 5 == 0).float(),
    }


def fill_buffer(agent, b: dict) -> None:
    """Observe the batch's transitions, so the agent has a batch to learn from (``update`` waits
    for ``batch_size`` transitions); which ones it learns from is ``agent.sample``'s."""
    for i in range(BATCH):
        agent.observe(
            Transition(
                b["obs"][i].numpy(),
                b["action"][i].numpy(),
                float(b["reward"][i]),
                b["next_obs"][i].numpy(),
                bool(b["terminated"][i]),
                False,
            )
        )


def sb3_update(model, b: dict, monkeypatch, draw_source: tuple, reward_shift: float = 0.0):
    """SB3's ``train(1)`` on batch ``b``; returns the random numbers it drew (its own)."""
    samples = ReplayBufferSamples(
        b["obs"],
        b["action"],
        b["next_obs"],
        b["terminated"][:, None],
        b["reward"][:, None] + reward_shift,
    )
    model.replay_buffer.sample = lambda batch_size, env=None: samples
    drawn = []
    owner, name = draw_source
    original = getattr(owner, name)

    def recorded(*args, **kwargs):
        out = original(*args, **kwargs)
        drawn.append(out.detach().clone())
        return out

    with monkeypatch.context() as m:
        m.setattr(owner, name, recorded)
        if b["obs"].dtype == torch.float64:  # SB3 casts Box observations to float32 (float())
            m.setattr(sb3_policies, "preprocess_obs", lambda obs, *_, **__: obs)
        model.train(gradient_steps=1, batch_size=BATCH)
    return drawn


def walkers_update(agent, b: dict, critic_noise, actor_noise) -> None:
    batch = Batch(*(b[k][None] for k in ("obs", "action", "reward", "next_obs", "terminated")))
    agent.sample = lambda: batch
    draws = iter([critic_noise, actor_noise])  # the update's draws, in its order
    agent.noise_like = lambda _x: next(draws)
    assert agent.update(), "walkers did not update"


TD3_DRAWS = (torch.Tensor, "normal_")  # noise = actions.clone().data.normal_(0, policy_noise)
GAUSSIAN_DRAWS = (torch.distributions.normal, "_standard_normal")  # SAC, CrossQ: Normal.rsample


def td3_noise(agent, drawn):
    """SB3 drew eps * policy_noise directly; walkers takes eps (policy_noise is 1/4, so the
    division and walkers' multiplication are exact)."""
    if agent.policy_noise == 0:  # DDPG: SB3 still draws normal_(0, 0); walkers draws nothing
        return None, None
    (noise,) = drawn
    return (noise / agent.policy_noise)[None], None


def sac_noise(agent, drawn):
    """SB3 draws eps for a ~ pi(.|s) first, then for a' ~ pi(.|s'); walkers' update
    draws (critic's a', actor's a)."""
    actor_eps, next_eps = drawn
    return next_eps[None], actor_eps[None]


def crossq_noise(agent, drawn):
    """CrossQ.train draws eps for a' ~ pi(.|s') first (the joint critic pass), then, on the
    delayed steps only, for a ~ pi(.|s) (the temperature's and the actor's step; walkers'
    delayed step with None would fail)."""
    next_eps, *actor_eps = drawn
    assert len(actor_eps) <= 1
    return next_eps[None], actor_eps[0][None] if actor_eps else None


def draws_and_noise(agent) -> tuple[tuple, Callable]:
    """Where SB3 draws its update's random numbers, and how they become walkers' draws."""
    if isinstance(agent, CrossQ):
        return GAUSSIAN_DRAWS, crossq_noise
    if isinstance(agent, SAC):
        return GAUSSIAN_DRAWS, sac_noise
    return TD3_DRAWS, td3_noise


def run_off_policy(agent, model, pairs, updates, monkeypatch, reward_shift=0.0) -> list[dict]:
    """``updates`` updates on both sides, each on a new batch (SB3's first batch with its rewards
    shifted by ``reward_shift``); the gaps after each."""
    draws, noise_of = draws_and_noise(agent)
    dtype = next(agent.actor.parameters()).dtype  # float64: CrossQ's test
    history = []
    for k in range(updates):
        b = {key: value.to(dtype) for key, value in make_batch(100 + k).items()}
        if k == 0:
            fill_buffer(agent, b)
        drawn = sb3_update(model, b, monkeypatch, draws, reward_shift if k == 0 else 0.0)
        walkers_update(agent, b, *noise_of(agent, drawn))
        history.append(gaps(pairs, agent, model))
    return history


# --- TD3 ----------------------------------------------------------------------------------------
TD3_HP = {"policy_noise": 0.25, "noise_clip": 0.5, "policy_delay": 2}


def td3_pair():
    agent, model = off_policy(TD3, "td3", **TD3_HP)
    pairs = deterministic_pairs(agent, model)
    load_sb3_weights_into_walkers(pairs, model)
    return agent, model, pairs


def test_td3_critic_and_actor_updates_match_sb3(monkeypatch):
    agent, model, pairs = td3_pair()
    first, second, third, fourth = run_off_policy(agent, model, pairs, 4, monkeypatch)
    # update 1: the critics only (policy_delay 2): no actor step, the targets unmoved, on both sides
    assert "actor/exp_avg" not in first and first["actor/weights"] == 0.0
    assert first["critic_target/weights"] == 0.0 and first["actor_target/weights"] == 0.0
    assert_agree(first)
    # update 2: critics, actor and both targets; 3 and 4 the same again, from the moved weights
    assert "actor/exp_avg" in second
    for found in (second, third, fourth):
        assert_agree(found)


def test_td3_parity_is_not_vacuous(monkeypatch):
    agent, model, pairs = td3_pair()
    *_, last = run_off_policy(agent, model, pairs, 2, monkeypatch, reward_shift=1.0)
    assert {"critic/weights", "critic/exp_avg", "actor/exp_avg"} <= differing(last)


# --- DDPG ---------------------------------------------------------------------------------------
def ddpg_pair():
    agent, model = off_policy(DDPG, "ddpg")
    pairs = deterministic_pairs(agent, model)
    load_sb3_weights_into_walkers(pairs, model)
    return agent, model, pairs


def test_ddpg_updates_match_sb3(monkeypatch):
    agent, model, pairs = ddpg_pair()
    assert len(model.critic.q_networks) == 1 and agent.critic.out.weight.shape[0] == 1
    for found in run_off_policy(agent, model, pairs, 2, monkeypatch):
        assert "actor/exp_avg" in found  # an actor step at every update
        assert_agree(found)


def test_ddpg_parity_is_not_vacuous(monkeypatch):
    agent, model, pairs = ddpg_pair()
    (found,) = run_off_policy(agent, model, pairs, 1, monkeypatch, reward_shift=1.0)
    assert {"critic/weights", "critic/exp_avg", "actor/exp_avg"} <= differing(found)


# --- SAC ---------------------------------------------------------------------------------------
def sac_pair(log_epsilon: float | None = None):
    """``log_epsilon``: SB3's epsilon in log(1 - tanh(u)^2 + epsilon) (None: SB3's 1e-6)."""
    agent, model = off_policy(SAC, "sac", alpha_init=0.5)
    if log_epsilon is not None:
        model.actor.action_dist.epsilon = log_epsilon
    pairs = sac_pairs(agent, model)
    load_sb3_weights_into_walkers(pairs, model)
    return agent, model, pairs


def sac_updates(monkeypatch, updates=3, reward_shift=0.0, log_epsilon=None) -> list[dict]:
    agent, model, pairs = sac_pair(log_epsilon)
    history = run_off_policy(agent, model, pairs, updates, monkeypatch, reward_shift)
    assert all(
        {"actor/exp_avg", "critic/exp_avg", "temperature/exp_avg"} <= set(h) for h in history
    )
    return history


def test_sac_critic_actor_and_temperature_updates_match_sb3(monkeypatch):
    """SB3 as shipped: weights, targets and moments agree to SAC_WEIGHT_ATOL and
    SAC_MOMENT_RTOL, the log epsilon's gap (isolated by the next test)."""
    for found in sac_updates(monkeypatch):
        assert_agree(found, SAC_WEIGHT_ATOL, SAC_MOMENT_RTOL)
        # alpha itself is equal: SB3 steps the temperature before the critics, walkers after the
        # actor, but both use the alpha from before the update in the critic target and actor loss
        assert found["temperature/weights"] <= WEIGHT_ATOL


def test_sac_differs_from_sb3_only_by_the_log_epsilon(monkeypatch):
    """SB3's log pi subtracts log(1 - tanh(u)^2 + 1e-6) (distributions.py,
    SquashedDiagGaussianDistribution.log_prob), walkers' the exact log(1 - tanh(u)^2)
    (networks.tanh_log_det_jacobian). With SB3's epsilon set to 0, SAC agrees as closely as the
    other twins (both critic losses are 1/2 sum MSE); with it, the actor's moments do not."""
    for found in sac_updates(monkeypatch, log_epsilon=0.0):
        assert_agree(found)
    (as_shipped,) = sac_updates(monkeypatch, updates=1)
    assert as_shipped["actor/exp_avg"] > MOMENT_RTOL


def test_sac_parity_is_not_vacuous(monkeypatch):
    (found,) = sac_updates(monkeypatch, updates=1, reward_shift=1.0)
    assert {"critic/weights", "critic/exp_avg", "actor/exp_avg"} <= differing(found)


# --- CrossQ (sb3-contrib) -----------------------------------------------------------------------
#: Small widths (actor HIDDEN, critics 64-64); the actor every 3rd update; momentum 0.1
#: (sb3-contrib's default 0.01) so the running statistics weigh; warm-up 2: a pass normalizes
#: with the corrected running statistics once its layer has done more than 2 passes.
CROSSQ_HP = {
    "critic_hidden_sizes": [64, 64],
    "policy_delay": 3,
    "renorm_momentum": 0.1,
    "renorm_warmup_steps": 2,
    "alpha_init": 0.5,
}
#: Six updates: the joint critic passes at updates 1-3 in batch statistics, 4-6 corrected (the
#: critics' renormalizations start at 0 passes); the actor's two passes (updates 3, 6) once in
#: batch statistics, once corrected (its renormalizations start at 2 passes).
CROSSQ_UPDATES = 6
RENORM_PASSES_BEFORE = {"critic": 0, "actor": 2}


@torch.no_grad()
def set_renorm_statistics(model) -> None:
    """SB3's renormalizations as in a run in progress, so no statistic is at its initial value
    and a mix-up of members or layers shows: scale and bias moved, running mean and variance off
    0 and 1, RENORM_PASSES_BEFORE passes done. load_sb3_weights_into_walkers copies them."""
    generator = torch.Generator().manual_seed(3)

    def noise(m):
        return torch.randn(m.num_features, generator=generator)

    for network, passes in RENORM_PASSES_BEFORE.items():
        for m in renorms(getattr(model, network)):
            m.scale.mul_(1 + 0.2 * noise(m))
            m.bias.add_(0.2 * noise(m))
            m.ra_mean.add_(0.5 * noise(m))
            m.ra_var.mul_((0.5 * noise(m)).exp())
            m.steps.fill_(passes)


@torch.no_grad()
def shrink_log_std_head(model) -> None:
    """SB3's log-std head at a tenth of nn.Linear's init. Its inputs renormalized to unit
    variance, log sigma reaches ~2 in batch statistics at that init: u = mu + sigma eps then
    passes ~9 for eps ~3, tanh(u) rounds to 1, and SB3's log(1 - tanh(u)^2) with its epsilon
    undone is -inf (walkers' stable form is finite)."""
    model.actor.log_std.weight.mul_(0.1)
    model.actor.log_std.bias.mul_(0.1)


def in_float64(agent, model) -> None:
    """Every network, statistic and temperature of both sides in float64 (Adam's moments follow
    on their first step; SB3's log alpha is a plain tensor: its data converted in place, so its
    optimizer still holds it)."""
    model.policy.double()
    model.log_ent_coef.data = model.log_ent_coef.data.double()
    for module in (agent.actor, agent.critic, agent.temperature):
        module.double()


def crossq_pair(log_epsilon: float | None = None, float64: bool = False):
    """``log_epsilon`` as :func:`sac_pair`'s: CrossQ's actor is SB3's squashed Gaussian."""
    pytest.importorskip("sb3_contrib")
    agent, model = build(CrossQ, "crossq", **OFF_POLICY, **CROSSQ_HP)
    if log_epsilon is not None:
        model.actor.action_dist.epsilon = log_epsilon
    if float64:
        in_float64(agent, model)
    set_renorm_statistics(model)
    shrink_log_std_head(model)
    pairs = crossq_pairs(agent, model)
    load_sb3_weights_into_walkers(pairs, model)
    return agent, model, pairs


def crossq_updates(monkeypatch, updates=CROSSQ_UPDATES, reward_shift=0.0, **pair):
    """``updates`` CrossQ updates on both sides (:func:`crossq_pair`'s ``pair`` options): the
    model and the gaps after each; the actor and alpha checked to step on the delayed updates
    only, on both sides."""
    agent, model, pairs = crossq_pair(**pair)
    history = run_off_policy(agent, model, pairs, updates, monkeypatch, reward_shift)
    # the actor's and alpha's gaps before any step: the weights and statistics loaded, no moments
    last_step = {"actor/weights": 0.0, "actor/running": 0.0, "actor/passes": 0.0}
    last_step["temperature/weights"] = 0.0
    for k, found in enumerate(history, start=1):
        actor = {key: v for key, v in found.items() if key.startswith(("actor/", "temperature/"))}
        if k % agent.policy_delay:  # the critics only: the actor and alpha as they were
            assert actor == last_step
        else:  # the temperature's and the actor's steps too
            assert {"actor/exp_avg", "temperature/exp_avg"} <= set(actor)
            last_step = actor
    return model, history


def test_crossq_critic_actor_and_temperature_updates_match_sb3_contrib(monkeypatch):
    """sb3-contrib's CrossQ.train, with SB3's log epsilon undone (set to 0, as for SAC above),
    in float64 (F64_WEIGHT_ATOL says why): every weight, renormalization (scale, bias, running
    mean and variance, pass count), alpha and Adam moment (actor, critics, temperature) agrees
    to float64 rounding, on critic-only and delayed updates, in the warm-up and past it."""
    model, history = crossq_updates(monkeypatch, log_epsilon=0.0, float64=True)
    for found in history:
        assert_agree(found, F64_WEIGHT_ATOL, F64_MOMENT_RTOL)
    # 6 joint critic passes, the last 3 past the warm-up; 2 actor passes, the second past it
    for network, passes in (("critic", 6), ("actor", 4)):
        assert {int(m.steps) for m in renorms(getattr(model, network))} == {passes}
    assert model.log_ent_coef.item() != pytest.approx(math.log(CROSSQ_HP["alpha_init"]))


def test_crossq_differs_from_sb3_contrib_only_by_the_log_epsilon(monkeypatch):
    """With SB3's epsilon left in (1e-6, in log pi of its squashed Gaussian: the actor's loss,
    the temperature's and the critics' target), the actor's moments part by more than
    MOMENT_RTOL at its first step (in float64, where nothing else parts them): a difference of
    its own, the one the previous test undoes. Its size is SAC's: within SAC_WEIGHT_ATOL and
    SAC_MOMENT_RTOL."""
    _, history = crossq_updates(monkeypatch, float64=True)
    assert history[CROSSQ_HP["policy_delay"] - 1]["actor/exp_avg"] > MOMENT_RTOL
    for found in history:
        assert_agree(found, SAC_WEIGHT_ATOL, SAC_MOMENT_RTOL)


def test_crossq_parity_is_not_vacuous(monkeypatch):
    _, history = crossq_updates(
        monkeypatch, updates=3, reward_shift=1.0, log_epsilon=0.0, float64=True
    )
    found = history[-1]  # critic and actor moved, the critics' statistics too
    assert {"critic/weights", "critic/exp_avg", "actor/exp_avg", "critic/running"} <= differing(
        found
    )


def test_crossq_renormalization_gradient_for_a_constant_feature_matches_sb3_contrib():
    """A feature constant over the batch (a ReLU unit off for every sample of the batch: batch
    variance 0), in the warm-up. sb3-contrib normalizes with the batch statistics alone
    (torch_layers.py, BatchRenorm.forward: the ``else`` of ``if self.steps > warmup_steps``),
    its input gradient finite. walkers computes both branches and picks with torch.where
    (renorm.py, EnsembleBatchRenorm._training_statistics), so the unpicked branch must not make
    a NaN of its zero gradient (sqrt's at a zero variance): it takes the square root of 1 there.
    Before that fix the NaN reached every weight gradient and the guard skipped the step.
    (Past the warm-up both sides' gradients
    are NaN/inf: the corrected branch divides by that sqrt's 0 on both.)"""
    pytest.importorskip("sb3_contrib")
    from sb3_contrib.common.torch_layers import BatchRenorm1d

    from walkers.agents.common.renorm import EnsembleBatchRenorm

    g = torch.Generator().manual_seed(4)
    x, upstream = torch.randn(2, BATCH, 3, generator=g)
    x[:, 1] = 0.0
    ours_x, theirs_x = x[None].clone().requires_grad_(), x.clone().requires_grad_()
    ours = EnsembleBatchRenorm(1, 3, momentum=0.01, warmup_steps=100).train()
    theirs = BatchRenorm1d(3, momentum=0.01, warmup_steps=100).train()
    (ours(ours_x)[0] * upstream).sum().backward()
    (theirs(theirs_x) * upstream).sum().backward()
    assert theirs_x.grad.isfinite().all()
    torch.testing.assert_close(ours_x.grad[0], theirs_x.grad)


# --- PPO: one rollout, walkers' minibatch order given to SB3 -------------------------------------
STEPS, MINIBATCHES, EPOCHS = 64, 4, 3
TERMINATED_AT, TRUNCATED_AT = 20, 45  # one episode ends in a terminal state, one at a time limit


def ppo_pair(**overrides):
    hp = {
        "n_steps": STEPS,
        "n_minibatches": MINIBATCHES,
        "n_epochs": EPOCHS,
        "lr": 1e-3,
        "anneal_lr": False,
        "ent_coef": 0.01,
        "normalize_obs": False,
        "normalize_reward": False,
    }
    agent, model = build(PPO, "ppo", **hp | overrides)
    pairs = ppo_pairs(agent, model)
    load_sb3_weights_into_walkers(pairs, model)
    return agent, model, pairs


def make_rollout(seed: int = 7) -> dict[str, torch.Tensor]:
    """Steps s_t, a_t (unclipped Gaussian samples), r_t, s'_t; s'_t = s_{t+1} inside an episode."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(STEPS + 1, OBS_DIM, generator=g)
    r = {
        "obs": obs[:-1],
        "next_obs": obs[1:].clone(),
        "action": 0.7 * torch.randn(STEPS, ACT_DIM, generator=g),
        "reward": 2 * torch.randn(STEPS, generator=g),
        "terminated": torch.zeros(STEPS),
        "episode_end": torch.zeros(STEPS, dtype=torch.bool),
    }
    for t in (TERMINATED_AT, TRUNCATED_AT):  # s' is the episode's last obs, not the next's first
        r["next_obs"][t] = torch.randn(OBS_DIM, generator=g)
        r["episode_end"][t] = True
    r["terminated"][TERMINATED_AT] = 1.0
    return r


def fill_walkers_rollout(agent, r: dict) -> None:
    for t in range(STEPS):
        agent.rollouts[0].add(
            bool(r["episode_end"][t]),
            obs=r["obs"][t].numpy(),
            action=r["action"][t].numpy(),
            reward=float(r["reward"][t]),
            terminated=float(r["terminated"][t]),
            next_obs=r["next_obs"][t].numpy(),
        )


@torch.no_grad()
def fill_sb3_rollout(model, r: dict, reward_shift: float = 0.0) -> None:
    """What SB3's collect_rollouts stores for these steps: values and log-probs of its policy, a
    time-limit truncation's reward plus gamma V(s') (on_policy_algorithm.py, "Handle timeout by
    bootstrapping"), episode starts, then the GAE from V of the last s'. ``reward_shift`` is
    added to the first reward."""
    buffer, policy = model.rollout_buffer, model.policy
    buffer.reset()
    values, log_probs, _ = policy.evaluate_actions(r["obs"], r["action"])
    next_values = policy.predict_values(r["next_obs"])
    rewards = r["reward"].numpy().copy()
    rewards[0] += reward_shift
    starts = np.r_[True, r["episode_end"][:-1].numpy()]
    for t in range(STEPS):
        if r["episode_end"][t] and not r["terminated"][t]:
            rewards[t] += model.gamma * next_values[t].item()
        buffer.add(
            r["obs"][t][None].numpy(),
            r["action"][t][None].numpy(),
            rewards[t : t + 1],
            starts[t : t + 1],
            values[t : t + 1],
            log_probs[t : t + 1],
        )
    buffer.compute_returns_and_advantage(next_values[-1:], dones=np.array([False]))


def run_ppo(agent, model, pairs, monkeypatch, reward_shift: float = 0.0) -> dict:
    """One update on both sides from the same rollout, SB3's minibatches in walkers' order."""
    r = make_rollout()
    fill_walkers_rollout(agent, r)
    fill_sb3_rollout(model, r, reward_shift)
    g = torch.Generator()
    g.set_state(agent.minibatch_generator.get_state())
    orders = [torch.randperm(STEPS, generator=g).numpy() for _ in range(EPOCHS)]

    def walkers_order(n: int) -> np.ndarray:  # RolloutBuffer.get's np.random.permutation
        assert n == STEPS
        return orders.pop(0)

    with monkeypatch.context() as m:
        m.setattr(np.random, "permutation", walkers_order)
        model.train()
    assert not orders, "SB3 ran fewer epochs than walkers will"
    assert agent.update(), "walkers did not update"
    return gaps(pairs, agent, model)


def test_ppo_update_without_value_clipping_matches_sb3(monkeypatch):
    """n_epochs x n_minibatches steps, the gradient norm clipped (max_grad_norm 0.5), advantages
    normalized per minibatch, an entropy bonus; SB3 with clip_range_vf=None."""
    agent, model, pairs = ppo_pair(clip_value_loss=False)
    assert model.clip_range_vf is None and model.vf_coef == agent.vf_coef / 2
    found = run_ppo(agent, model, pairs, monkeypatch)
    assert agent.optimizer.state[agent.policy.log_std]["step"] == EPOCHS * MINIBATCHES
    assert_agree(found)


def sb3_value_loss(values, old_values, returns, clip_coef):
    """SB3's value loss in walkers' terms: 1/2 (R - V_pred)^2, V_pred = V clipped to within
    clip_coef of V_old (ppo.py, PPO.train), instead of walkers' max of clipped and unclipped."""
    if clip_coef is not None:
        values = old_values + (values - old_values).clamp(-clip_coef, clip_coef)
    return 0.5 * (values - returns).pow(2)


def test_ppo_value_clipping_is_the_one_difference(monkeypatch):
    """clip_value_loss=true (SB3: clip_range_vf=clip_coef). Walkers clips as ppo2 (max of the
    clipped and unclipped errors, walkers.agents.ppo.value_loss), SB3 clips V itself. With the
    gradient norm unclipped (it would couple the policy's step to the value's gradient):
    the policy, its moments included, agrees; the value net differs; and with SB3's form put in
    place of walkers' value_loss, everything agrees again."""
    hp = {"clip_value_loss": True, "max_grad_norm": None}
    agent, model, pairs = ppo_pair(**hp)
    found = run_ppo(agent, model, pairs, monkeypatch)
    assert_agree({k: v for k, v in found.items() if k.startswith("policy/")})
    assert {"value/weights", "value/exp_avg", "value/exp_avg_sq"} <= differing(found)

    agent, model, pairs = ppo_pair(**hp)
    monkeypatch.setattr("walkers.agents.ppo.value_loss", sb3_value_loss)
    assert_agree(run_ppo(agent, model, pairs, monkeypatch))


def test_ppo_parity_is_not_vacuous(monkeypatch):
    agent, model, pairs = ppo_pair(clip_value_loss=False)
    found = run_ppo(agent, model, pairs, monkeypatch, reward_shift=1.0)
    assert {"policy/weights", "policy/exp_avg", "value/weights", "value/exp_avg"} <= differing(
        found
    )
