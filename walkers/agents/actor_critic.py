"""Off-policy actor-critic with experience replay: the shared core of TD3, DDPG and SAC.

The core holds what the three share: replay buffers, the actor and critic ensembles and their
targets, Adam, the uniform random warm-up, the NaN/inf guard, populations and checkpoints, and
the loop of one update (:meth:`ActorCritic.update`): sample a mini-batch, step the critics onto
their target, then every ``policy_delay`` updates step the actor (and what follows it) and move
the targets. What makes an algorithm is its own module, readable next to its paper:

- :mod:`walkers.agents.td3`: TD3's target (clipped smoothing noise, min of the twin critics),
  its deterministic policy gradient, delayed updates and Gaussian exploration (Algorithm 1 of
  Fujimoto et al. 2018); :mod:`walkers.agents.ddpg` is TD3 with those three off;
- :mod:`walkers.agents.sac`: the soft target, the reparameterized actor loss, the temperature
  and exploration by the policy's own samples.

Every network is an ensemble with a leading *member* dimension: a single agent is a population of
one, ``population=K`` trains K independent seeds (``seed, seed + 1, ...``) with one batched
matmul a layer for all of them. Each member has its own replay buffer, exploration noise and RNG
(:class:`Member`); losses are sums of per-member losses, so each member's gradient is its own,
and Adam, being elementwise, keeps members independent under one optimizer. Cutting a member out
as a single agent and loading it back is :mod:`walkers.agents.population`.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from walkers.agents import population as members_io
from walkers.agents.base import Agent, Transition, resolve_device
from walkers.agents.health import NonFiniteGuard, guarded_step
from walkers.agents.networks import EnsembleActor, make_critic, soft_update
from walkers.agents.noise import GaussianNoise
from walkers.agents.population import Member
from walkers.data.replay import Batch, ReplayBuffer
from walkers.seeding import numpy_rng, stream_seeds

log = logging.getLogger("walkers")


class ActorCritic(Agent):
    """The shared core (see the module docstring). A subclass sets :attr:`num_critics`,
    :attr:`policy_delay` (or an attribute of that name in its constructor), its actor class, and
    implements the hooks: :meth:`exploration_noise`, :meth:`policy`, :meth:`update_noise`,
    :meth:`next_value` and :meth:`actor_loss` (optionally :meth:`after_actor_step`)."""

    actor_class: type[nn.Module] = EnsembleActor  # built as (n, obs, act, hidden, low, high)
    uses_actor_target = True  # a target actor pi' (DDPG, TD3); SAC has none
    num_critics = 2  # critics per member
    policy_delay = 1  # critic updates per actor update and target move

    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        lr: float,
        batch_size: int,
        learning_starts: int,
        hidden_sizes: Sequence[int],
        gamma: float,
        tau: float,
        buffer_size: int,
        actor_lr: float | None = None,
        critic_lr: float | None = None,
        critic_architecture: str | None = None,
        critic_hidden_sizes: Sequence[int] | None = None,
        population: int = 1,
        compile: bool,
        device: str = "cpu",
        seed: int = 0,
    ):
        self.device = resolve_device(device)
        self.batch_size, self.learning_starts = int(batch_size), int(learning_starts)
        self.gamma, self.tau = gamma, tau
        self.population = int(population)
        self.action_low = np.asarray(action_low, dtype=np.float32)
        self.action_high = np.asarray(action_high, dtype=np.float32)
        act_dim = len(self.action_low)

        torch.manual_seed(seed)
        self.actor = self.actor_class(
            self.population, obs_dim, act_dim, hidden_sizes, action_low, action_high
        ).to(self.device)
        critic_hidden = hidden_sizes if critic_hidden_sizes is None else critic_hidden_sizes
        self.critic = make_critic(
            critic_architecture or "mlp",  # TD3's and SAC's; DDPG declares the choice
            obs_dim,
            act_dim,
            critic_hidden,
            self.num_critics * self.population,
        ).to(self.device)
        self.actor_target = (
            copy.deepcopy(self.actor).requires_grad_(False) if self.uses_actor_target else None
        )
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_optimizer = torch.optim.Adam(
            self.actor.parameters(), lr=actor_lr or lr, fused=True
        )
        self.critic_optimizer = torch.optim.Adam(
            self.critic.parameters(), lr=critic_lr or lr, fused=True
        )
        self.low_t = torch.as_tensor(self.action_low, device=self.device)
        self.high_t = torch.as_tensor(self.action_high, device=self.device)

        self.members = []
        for member_seed in range(seed, seed + self.population):
            rng = numpy_rng(member_seed, "exploration")
            replay_seed = stream_seeds(member_seed, "replay")[0]
            self.members.append(
                Member(
                    rng,
                    self.exploration_noise(rng, act_dim),
                    ReplayBuffer(buffer_size, obs_dim, act_dim, self.device, replay_seed),
                )
            )
        self.steps = 0  # transitions observed (per member)
        self.num_updates = 0  # critic updates done
        # Uniform random actions while steps < random_until, no updates while steps < update_after:
        # both learning_starts, unless a run resumed without its replay buffer refills it.
        self.random_until = self.update_after = self.learning_starts
        self.refilled_at: int | None = None  # the step a resume without the buffer refilled from
        self.guard = NonFiniteGuard(self.device, (self.population,))
        self._critic_loss, self._actor_loss = self.critic_loss, self.actor_loss
        if compile:
            self._compile_losses()

    def _compile_losses(self) -> None:
        """``compile=True``: the two loss computations, forward and backward, through
        ``torch.compile`` (fused elementwise work, less dispatch). On CUDA with CUDA graphs
        (``reduce-overhead``), where a small update is launch-bound. The optimizer steps stay
        eager: fused Adam is one kernel already and keeps the NaN guard's step skip."""
        mode = "reduce-overhead" if self.device.type == "cuda" else None
        self._critic_loss = torch.compile(self.critic_loss, mode=mode)
        self._actor_loss = torch.compile(self.actor_loss, mode=mode)

    @property
    def buffer(self) -> ReplayBuffer:
        """A single agent's replay buffer (member 0's in a population)."""
        return self.members[0].buffer

    # --- acting: one observation and one transition per member, in member order --------------
    def act_population(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """``(K, act_dim)`` actions for ``(K, obs_dim)`` observations."""
        if explore and self.steps < self.random_until:  # uniform random warm-up
            uniform = [m.rng.uniform(self.action_low, self.action_high) for m in self.members]
            return np.stack(uniform).astype(np.float32)
        noise = np.stack([m.noise.sample() for m in self.members]) if explore else None
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            return self.policy(obs_t.unsqueeze(1), noise)

    def exploration_noise(self, rng: np.random.Generator, act_dim: int) -> GaussianNoise:
        """A member's exploration noise process, drawing from its exploration stream ``rng``."""
        raise NotImplementedError

    def policy(self, obs: torch.Tensor, noise: np.ndarray | None) -> np.ndarray:
        """``(K, act_dim)`` actions for ``(K, 1, obs_dim)`` observations; ``noise``: each
        member's exploration noise sample ``(K, act_dim)``, or None for the greedy policy."""
        raise NotImplementedError

    def observe_population(self, transitions: Sequence[Transition]) -> None:
        for member, t in zip(self.members, transitions, strict=True):
            member.buffer.add(t.obs, t.action, t.reward, t.next_obs, t.terminated, t.episode_over)
            if t.episode_over:
                member.noise.reset()
        self.steps += 1

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        return self.act_population(obs[None], explore)[0]

    def observe(self, t: Transition) -> None:
        self.observe_population([t])

    # --- learning: the loop of one update --------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if self.steps < self.update_after or len(self.buffer) < self.batch_size:
            return {}
        self.num_updates += 1
        b = self.sample()  # a mini-batch of N transitions (s, a, r, s', d) per member
        critic_noise, actor_noise = self.update_noise(b)

        # Critics: y = r + gamma (1 - d) V'(s');  theta_i <- argmin N^-1 sum (y - Q_i)^2
        critic_loss, q_mean = self._critic_loss(b, critic_noise)
        critic_bad = guarded_step(self.critic_optimizer, critic_loss, self.num_critics)
        actor_bad = None  # this update's actor step skipped (None: no actor step this time)
        metrics = {"loss/critic": _logged(critic_loss), "train/q_mean": _logged(q_mean)}

        # Every d updates: the actor's step (and the algorithm's step after it), then the soft
        # target updates theta' <- tau theta + (1 - tau) theta', phi' <- tau phi + (1 - tau) phi'.
        if self.num_updates % self.policy_delay == 0:
            self.critic.requires_grad_(False)  # the actor's gradient only: no critic weight grads
            actor_loss, actor_info = self._actor_loss(b.obs, actor_noise)
            self.critic.requires_grad_(True)
            # critic_bad, not the critic loss: under CUDA graphs the actor-loss run has already
            # reclaimed the critic-loss run's outputs.
            actor_bad = guarded_step(self.actor_optimizer, actor_loss, 1, also_bad=critic_bad)
            metrics["loss/actor"] = _logged(actor_loss)
            metrics |= self.after_actor_step(actor_info, actor_bad)
            soft_update(self.critic_target, self.critic, self.tau)
            if self.actor_target is not None:
                soft_update(self.actor_target, self.actor, self.tau)
        # skipped: a critic step, or the actor's latest step, was (health/*, divergence_patience)
        self.guard.record(critic_bad, delayed_bad=actor_bad)
        return metrics | self.guard.metrics()

    def update_noise(self, b: Batch) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """The random numbers of one update, for the critic loss and the actor loss: drawn
        outside them so a compiled update draws the same numbers as eager."""
        raise NotImplementedError

    def critic_loss(
        self, b: Batch, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-member critic loss ``(K,)`` (the sum of its critics' MSEs) and mean Q ``(K,)``.

        Every Q_i regresses onto y = r + gamma * (1 - terminated) * V'(s'), V' being
        :meth:`next_value` (``noise``: the critic's part of :meth:`update_noise`).
        """
        K, C = self.population, self.num_critics
        with torch.no_grad():
            y = b.reward + self.gamma * (1.0 - b.terminated) * self.next_value(b.next_obs, noise)
        q = self.critic(self._per_critic(b.obs), self._per_critic(b.action)).unflatten(0, (K, C))
        member_loss = (q - y.unsqueeze(1)).pow(2).mean(dim=2).sum(dim=1)
        return member_loss, q.detach().mean(dim=(1, 2))

    def next_value(self, next_obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """V'(s') ``(K, N)``, what the critics' target bootstraps from (``noise``: the critic's
        part of :meth:`update_noise`)."""
        raise NotImplementedError

    def min_target_q(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """min_j Q'_j(s, a) ``(K, N)`` over each member's target critics (clipped double-Q)."""
        next_q = self.critic_target(self._per_critic(obs), self._per_critic(action))
        return next_q.unflatten(0, (self.population, self.num_critics)).min(dim=1).values

    def actor_loss(
        self, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Per-member actor loss ``(K,)`` and what :meth:`after_actor_step` needs of it."""
        raise NotImplementedError

    def after_actor_step(
        self, actor_info: torch.Tensor | None, skip: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """A step after the actor's, before the target updates (SAC: the temperature); its
        metrics. ``skip``: members whose update is skipped (a non-finite loss)."""
        return {}

    def sample(self) -> Batch:
        """One mini-batch per member, stacked: ``(K, batch, ...)`` tensors."""
        batches = [m.buffer.sample(self.batch_size) for m in self.members]
        return Batch(*(torch.stack(field) for field in zip(*batches, strict=True)))

    def _per_critic(self, x: torch.Tensor) -> torch.Tensor:
        """Each member's inputs once per critic: ``(K, N, d)`` -> ``(K * C, N, d)`` (a view for
        a single agent)."""
        return x.unsqueeze(1).expand(-1, self.num_critics, -1, -1).flatten(0, 1)

    # --- checkpoints: a single agent's is member 0 cut out, a population's its members' --------
    def state_dict(self, with_buffer: bool = False) -> dict:
        if self.population == 1:
            return members_io.member_state_dict(self, 0, with_buffer)
        return {
            "members": [
                members_io.member_state_dict(self, i, with_buffer) for i in range(self.population)
            ]
        }

    def load_state_dict(self, state: dict) -> None:
        for i, member_state in enumerate(state.get("members", [state])):
            members_io.load_member_state_dict(self, i, member_state)

    def load_counters(self, state: dict) -> None:
        self.steps, self.num_updates = state["steps"], state["num_updates"]
        self.random_until = state.get("random_until", self.learning_starts)
        self.update_after = state.get("update_after", self.learning_starts)

    def refill_if_lost(self, buffer_state: dict) -> None:
        """A checkpoint without its transitions: refill the buffer before updating again.

        Updating at once would fit the critics to the few transitions collected since (silently
        a different experiment). Instead the agent collects ``max(learning_starts, batch_size)``
        transitions first: of the current policy with exploration noise, or uniform random ones
        if the run was interrupted in its warm-up (the warm-up restarts whole).
        """
        if "data" in buffer_state or buffer_state.get("size", 0) == 0:
            return
        refill = max(self.learning_starts, self.batch_size)
        in_warmup = self.steps < self.random_until
        if in_warmup:
            self.random_until = self.steps + refill
        self.update_after = max(self.update_after, self.steps + refill)
        self.refilled_at = self.steps
        log.warning(
            "resumed at step %d without the replay buffer's %d transitions: refilling %d "
            "transitions (%s) before updating again at step %d",
            self.steps,
            buffer_state["size"],
            refill,
            "uniform random: the warm-up again" if in_warmup else "current policy with noise",
            self.update_after,
        )

    def resume_notes(self) -> dict[str, str]:
        if self.refilled_at is None:
            return {}
        return {"walkers.buffer_refill": f"steps {self.refilled_at}-{self.update_after}"}

    # --- a population's members one at a time (walkers.agents.population) -------------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        """Member ``i``'s slice of the leading dimension of every per-member part, by attribute
        name: modules (their state dicts) and optimizers (their Adam moments). A member's
        checkpoint holds these parts, cut; a subclass with more parts adds them here."""
        own, critics = slice(i, i + 1), slice(i * self.num_critics, (i + 1) * self.num_critics)
        cuts = {"actor": own, "critic": critics, "actor_target": own, "critic_target": critics}
        if self.actor_target is None:
            del cuts["actor_target"]
        return cuts | {"actor_optimizer": own, "critic_optimizer": critics}

    def member_policy(self, i: int) -> members_io.MemberAgent:
        """Member ``i`` as an agent of its own (evaluation rollouts, its checkpoints)."""
        return members_io.MemberAgent(self, i)

    def member_state_dict(self, i: int, with_buffer: bool = False) -> dict:
        return members_io.member_state_dict(self, i, with_buffer)

    def load_member_state_dict(self, i: int, state: dict) -> None:
        members_io.load_member_state_dict(self, i, state)


def _logged(x: torch.Tensor) -> torch.Tensor:
    """A per-member ``(K,)`` diagnostic to log: a copy, as CUDA graphs reuse their outputs."""
    return x.detach().clone()
