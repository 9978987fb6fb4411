"""Deterministic off-policy actor-critic with experience replay: the core of DDPG and TD3.

TD3 (Fujimoto et al. 2018) is this core with ``num_critics=2`` (clipped double-Q),
``policy_noise > 0`` (target policy smoothing) and ``policy_delay=2`` (delayed actor and target
updates). DDPG as the TD3 paper's "our DDPG" is the same core with one critic, no smoothing and
no delay. The update in :meth:`ActorCritic.update` follows Algorithm 1 of the TD3 paper line by
line.

``population=K`` trains K independent seeds (``seed, seed + 1, ...``) in one agent: actors and
critics are ensembles with a leading member dimension (one batched matmul per layer for all),
each member has its own replay buffer, exploration noise and RNG, and the losses are sums of
per-member losses, so each member's gradient is its own. Adam is elementwise, so one optimizer
keeps members independent; a member whose loss is NaN/inf has its gradients zeroed for that
update (the others step normally). :meth:`ActorCritic.member_state_dict` cuts one member out as
an ordinary single-agent checkpoint. With ``population=1`` (the default) tensors carry no member
dimension and nothing changes.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence

import numpy as np
import torch

from walkers.agents.base import Agent, Transition, resolve_device
from walkers.agents.health import NonFiniteGuard
from walkers.buffers import Batch, ReplayBuffer
from walkers.nn import Actor, EnsembleActor, make_critic, soft_update
from walkers.seeding import numpy_rng, stream_seeds

log = logging.getLogger("walkers")


class GaussianNoise:
    """i.i.d. N(0, sigma) exploration noise."""

    def __init__(self, sigma: float, size: int, rng: np.random.Generator):
        self.sigma, self.size, self.rng = sigma, size, rng

    def sample(self) -> np.ndarray:
        return self.rng.normal(0.0, self.sigma, self.size)

    def reset(self) -> None:
        pass

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class OrnsteinUhlenbeckNoise(GaussianNoise):
    """Temporally correlated noise x <- x + theta (0 - x) dt + sigma sqrt(dt) N(0, 1) (DDPG paper).

    Reset to zero at the start of every episode.
    """

    def __init__(self, sigma, size, rng, theta: float = 0.15, dt: float = 1e-2):
        super().__init__(sigma, size, rng)
        self.theta, self.dt = theta, dt
        self.x = np.zeros(size)

    def sample(self) -> np.ndarray:
        noise = self.rng.normal(0.0, 1.0, self.size)
        self.x = self.x - self.theta * self.x * self.dt + self.sigma * np.sqrt(self.dt) * noise
        return self.x

    def reset(self) -> None:
        self.x = np.zeros(self.size)

    def state_dict(self) -> dict:
        return {"x": self.x.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.x = state["x"].copy()


NOISE_TYPES = {"gaussian": GaussianNoise, "ou": OrnsteinUhlenbeckNoise}
ADAM_MOMENTS = ("exp_avg", "exp_avg_sq")


class ActorCritic(Agent):
    """The shared core; defaults are TD3's reference hyperparameters (see conf/algo/td3.yaml)."""

    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        lr: float = 3e-4,
        batch_size: int = 256,
        learning_starts: int = 25_000,
        hidden_sizes: Sequence[int] = (256, 256),
        gamma: float = 0.99,
        tau: float = 0.005,
        num_critics: int = 2,
        policy_noise: float = 0.2,
        noise_clip: float = 0.5,
        policy_delay: int = 2,
        exploration_noise: float = 0.1,
        buffer_size: int = 1_000_000,
        actor_lr: float | None = None,
        critic_lr: float | None = None,
        critic_architecture: str = "mlp",
        critic_hidden_sizes: Sequence[int] | None = None,
        noise_type: str = "gaussian",
        population: int = 1,
        compile: bool = False,
        device: str = "cpu",
        seed: int = 0,
    ):
        if noise_type not in NOISE_TYPES:
            raise ValueError(f"noise_type={noise_type!r} is not one of {sorted(NOISE_TYPES)}")
        self.device = resolve_device(device)
        self.batch_size, self.learning_starts = int(batch_size), int(learning_starts)
        self.gamma, self.tau = gamma, tau
        self.policy_noise, self.noise_clip, self.policy_delay = (
            policy_noise,
            noise_clip,
            policy_delay,
        )

        self.action_low = np.asarray(action_low, dtype=np.float32)
        self.action_high = np.asarray(action_high, dtype=np.float32)
        act_dim = len(self.action_low)
        self.population, self.num_critics = int(population), num_critics
        seeds = [seed + i for i in range(self.population)]
        self.rngs = [numpy_rng(s, "exploration") for s in seeds]  # one per member
        self.rng = self.rngs[0]
        half_range = (self.action_high - self.action_low) / 2
        self.noises = [NOISE_TYPES[noise_type](exploration_noise, act_dim, r) for r in self.rngs]
        self.noise = self.noises[0]
        self.noise_scale = half_range  # noise std is given as a fraction of the half-range

        torch.manual_seed(seed)
        if self.population == 1:
            actor = Actor(obs_dim, act_dim, hidden_sizes, action_low, action_high)
        else:
            actor = EnsembleActor(
                self.population, obs_dim, act_dim, hidden_sizes, action_low, action_high
            )
        self.actor = actor.to(self.device)
        critic_hidden = hidden_sizes if critic_hidden_sizes is None else critic_hidden_sizes
        self.critic = make_critic(
            critic_architecture, obs_dim, act_dim, critic_hidden, num_critics * self.population
        ).to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_optimizer = torch.optim.Adam(
            self.actor.parameters(), lr=actor_lr or lr, fused=True
        )
        self.critic_optimizer = torch.optim.Adam(
            self.critic.parameters(), lr=critic_lr or lr, fused=True
        )
        self.low_t = torch.as_tensor(self.action_low, device=self.device)
        self.high_t = torch.as_tensor(self.action_high, device=self.device)

        self.buffers = [
            ReplayBuffer(buffer_size, obs_dim, act_dim, self.device, stream_seeds(s, "replay")[0])
            for s in seeds
        ]
        self.buffer = self.buffers[0]
        self.steps = 0  # transitions observed (per member)
        self.num_updates = 0  # critic updates done
        # Uniform random actions while steps < random_until, no updates while steps < update_after:
        # both learning_starts, unless a run resumed without its replay buffer refills it.
        self.random_until = self.update_after = self.learning_starts
        self.refilled_at: int | None = None  # the step a resume without the buffer refilled from
        shape = () if self.population == 1 else (self.population,)
        self.guard = NonFiniteGuard(self.device, shape)
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

    # --- acting -------------------------------------------------------------------------------
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        if explore and self.steps < self.random_until:  # uniform random warm-up
            return self.rng.uniform(self.action_low, self.action_high).astype(np.float32)
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            action = self.actor(obs_t.unsqueeze(0))[0].cpu().numpy()
        if explore:
            action = action + self.noise.sample() * self.noise_scale
            action = np.clip(action, self.action_low, self.action_high)
        return action.astype(np.float32)

    def observe(self, t: Transition) -> None:
        self.buffer.add(t.obs, t.action, t.reward, t.next_obs, t.terminated, t.episode_over)
        self.steps += 1
        if t.episode_over:
            self.noise.reset()

    # --- a population: one observation and one transition per member, in member order -------
    def act_population(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """``(K, act_dim)`` actions for ``(K, obs_dim)`` observations."""
        if explore and self.steps < self.random_until:
            uniform = [r.uniform(self.action_low, self.action_high) for r in self.rngs]
            return np.stack(uniform).astype(np.float32)
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            actions = self.actor(obs_t.unsqueeze(1))[:, 0].cpu().numpy()
        if explore:
            noise = np.stack([n.sample() for n in self.noises]) * self.noise_scale
            actions = np.clip(actions + noise, self.action_low, self.action_high)
        return actions.astype(np.float32)

    def observe_population(self, transitions: list[Transition]) -> None:
        for buffer, noise, t in zip(self.buffers, self.noises, transitions, strict=True):
            buffer.add(t.obs, t.action, t.reward, t.next_obs, t.terminated, t.episode_over)
            if t.episode_over:
                noise.reset()
        self.steps += 1

    def member_policy(self, i: int) -> MemberAgent:
        """Member ``i`` as an agent of its own (evaluation rollouts, its checkpoints)."""
        return MemberAgent(self, i)

    # --- learning -----------------------------------------------------------------------------
    def _sample(self) -> Batch:
        """A batch: ``(batch, ...)`` tensors, or ``(K, batch, ...)`` (one per member) for K > 1."""
        if self.population == 1:
            return self.buffer.sample(self.batch_size)
        batches = [buffer.sample(self.batch_size) for buffer in self.buffers]
        return Batch(*(torch.stack(field) for field in zip(*batches, strict=True)))

    def _per_critic(self, x: torch.Tensor) -> torch.Tensor:
        """Each member's inputs for each of its critics: ``(K, B, d)`` -> ``(K * C, B, d)``."""
        return x if x.dim() == 2 else x.repeat_interleave(self.num_critics, dim=0)

    def _per_member(self, x: torch.Tensor) -> torch.Tensor:
        """A ``(K,)`` diagnostic; a scalar for a single agent. A copy: CUDA graphs reuse outputs."""
        return (x.detach()[0] if self.population == 1 else x.detach()).clone()

    def _skip_bad_members(self, optimizer, bad: torch.Tensor, copies: int) -> None:
        """Make the next ``optimizer.step()`` skip members whose ``bad`` is 1, without a sync.

        A single agent: fused Adam skips its whole step (``found_inf``). A population: the bad
        members' gradients are zeroed (NaN included) and the step is skipped only if all are bad.
        ``copies``: parameter members per agent member (the critics per member).
        """
        if self.population == 1:
            optimizer.found_inf = bad[0]
            return
        optimizer.found_inf = bad.min()
        skip = (bad > 0).repeat_interleave(copies).view(-1, 1, 1)
        for group in optimizer.param_groups:
            for param in group["params"]:
                if param.grad is not None:
                    param.grad.masked_fill_(skip, 0.0)

    def critic_loss(
        self, b: Batch, smoothing_noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-member critic loss ``(K,)`` and mean Q ``(K,)`` (TD3 paper, Algorithm 1).

        Every Q_i regresses onto y = r + gamma * (1 - terminated) * min_j Q'_j(s', a~) with
        a~ = clip(pi'(s') + clip(sigma * eps, -c, c), low, high), eps ~ N(0, 1) given as
        ``smoothing_noise`` (drawn outside so a compiled update draws the same numbers as eager).
        """
        K, C = self.population, self.num_critics
        with torch.no_grad():
            next_action = self.actor_target(b.next_obs)
            if smoothing_noise is not None:
                eps = smoothing_noise * self.policy_noise
                eps = eps.clamp(-self.noise_clip, self.noise_clip) * self.actor.action_scale
                next_action = (next_action + eps).clamp(self.low_t, self.high_t)
            next_q = self.critic_target(self._per_critic(b.next_obs), self._per_critic(next_action))
            next_q = next_q.unflatten(0, (K, C)).min(dim=1).values  # (K, batch)
            target = b.reward + self.gamma * (1.0 - b.terminated) * next_q
        q = self.critic(self._per_critic(b.obs), self._per_critic(b.action)).unflatten(0, (K, C))
        member_loss = (q - target.unsqueeze(1)).pow(2).mean(dim=2).sum(dim=1)
        return member_loss, q.detach().mean(dim=(1, 2))

    def actor_loss(self, obs: torch.Tensor) -> torch.Tensor:
        """Per-member actor loss ``(K,)``: -Q_1(s, pi(s)), the deterministic policy gradient."""
        q_pi = self.critic(obs, self.actor(obs), members=slice(0, None, self.num_critics))
        return -q_pi.mean(dim=-1)

    def update(self) -> dict[str, torch.Tensor]:
        if self.steps < self.update_after or len(self.buffer) < self.batch_size:
            return {}
        self.num_updates += 1
        b = self._sample()

        smoothing_noise = torch.randn_like(b.action) if self.policy_noise > 0 else None
        member_critic_loss, q_mean = self._critic_loss(b, smoothing_noise)
        self.critic_optimizer.zero_grad(set_to_none=True)
        member_critic_loss.sum().backward()
        # NaN/inf guard without a host sync (see _skip_bad_members).
        critic_bad = NonFiniteGuard.bad_members(member_critic_loss)
        self._skip_bad_members(self.critic_optimizer, critic_bad, copies=self.num_critics)
        self.critic_optimizer.step()
        self.guard.record(self._per_member(critic_bad))
        metrics = {
            "loss/critic": self._per_member(member_critic_loss),
            "train/q_mean": self._per_member(q_mean),
        }

        # Delayed policy update: maximize Q_1(s, pi(s)), then move the targets.
        if self.num_updates % self.policy_delay == 0:
            self.critic.requires_grad_(False)  # the actor's gradient only: no critic weight grads
            member_actor_loss = self._actor_loss(b.obs)
            self.critic.requires_grad_(True)
            self.actor_optimizer.zero_grad(set_to_none=True)
            member_actor_loss.sum().backward()
            # critic_bad, not the critic loss: under CUDA graphs the actor-loss run has already
            # reclaimed the critic-loss run's outputs.
            bad = torch.maximum(critic_bad, NonFiniteGuard.bad_members(member_actor_loss))
            self._skip_bad_members(self.actor_optimizer, bad, copies=1)
            self.actor_optimizer.step()
            soft_update(self.critic_target, self.critic, self.tau)
            soft_update(self.actor_target, self.actor, self.tau)
            metrics["loss/actor"] = self._per_member(member_actor_loss)
        return metrics | self.guard.metrics()

    # --- checkpoints --------------------------------------------------------------------------
    def state_dict(self, with_buffer: bool = False) -> dict:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "steps": self.steps,
            "num_updates": self.num_updates,
            "random_until": self.random_until,
            "update_after": self.update_after,
            "rng": self.rng.bit_generator.state,
            "noise": self.noise.state_dict(),
            "buffer": self.buffer.state_dict(with_data=with_buffer),
            "guard": self.guard.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        for name in ("actor", "critic", "actor_target", "critic_target"):
            getattr(self, name).load_state_dict(state[name])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self._load_counters(state)
        self.rng.bit_generator.state = state["rng"]
        self.noise.load_state_dict(state["noise"])
        self.buffer.load_state_dict(state["buffer"])
        if "guard" in state:
            self.guard.load_state_dict(state["guard"])
        self._refill_if_lost(state["buffer"])

    def resume_notes(self) -> dict[str, str]:
        if self.refilled_at is None:
            return {}
        return {"walkers.buffer_refill": f"steps {self.refilled_at}-{self.update_after}"}

    def _load_counters(self, state: dict) -> None:
        self.steps, self.num_updates = state["steps"], state["num_updates"]
        self.random_until = state.get("random_until", self.learning_starts)
        self.update_after = state.get("update_after", self.learning_starts)

    def _refill_if_lost(self, buffer_state: dict) -> None:
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

    def member_state_dict(self, i: int, with_buffer: bool = False) -> dict:
        """Member ``i`` of a population as a single agent's :meth:`state_dict`.

        Networks, targets, Adam moments, counters, RNG, noise, buffer and guard of that member
        only, in the single-agent layout: a member's checkpoint loads into an ordinary agent
        (``walkers.evaluate``, ``walkers.collect``, or ``resume=`` to continue it alone), or back
        into a population (:meth:`load_member_state_dict`).
        """
        critic_cut = self._critic_slice(i)

        def critic_state(module) -> dict:
            return {k: v[critic_cut].clone() for k, v in module.state_dict().items()}

        def optimizer_state(optimizer, cut) -> dict:
            state = optimizer.state_dict()
            for index, moments in list(state["state"].items()):
                # a new dict: state_dict() shares the live tensors
                state["state"][index] = moments | {key: cut(moments[key]) for key in ADAM_MOMENTS}
            return state

        def actor_cut(x):  # EnsembleLinear weight (K, in, out) -> Linear (out, in)
            return x[i].T.contiguous() if x.shape[1] != 1 else x[i, 0].clone()

        return {
            "actor": self.actor.member_state(i),
            "critic": critic_state(self.critic),
            "actor_target": self.actor_target.member_state(i),
            "critic_target": critic_state(self.critic_target),
            "actor_optimizer": optimizer_state(self.actor_optimizer, actor_cut),
            "critic_optimizer": optimizer_state(self.critic_optimizer, lambda x: x[critic_cut]),
            "steps": self.steps,
            "num_updates": self.num_updates,
            "random_until": self.random_until,
            "update_after": self.update_after,
            "rng": self.rngs[i].bit_generator.state,
            "noise": self.noises[i].state_dict(),
            "buffer": self.buffers[i].state_dict(with_data=with_buffer),
            "guard": {
                "skipped": self.guard.skipped[i].item(),
                "in_a_row": self.guard.in_a_row[i].item(),
            },
        }

    @torch.no_grad()
    def load_member_state_dict(self, i: int, state: dict) -> None:
        """Load a single agent's :meth:`state_dict` into member ``i`` of this population.

        The inverse of :meth:`member_state_dict`: K runs resumed together continue as one
        population (``resume=[id,id,...]``). Counters (env steps, updates, Adam's step count)
        are shared, so every member must be at the same update (the caller checks); they are
        taken from the last member loaded.
        """
        critic_cut = self._critic_slice(i)
        for name in ("actor", "actor_target"):
            getattr(self, name).load_member_state(i, state[name])
        for name in ("critic", "critic_target"):
            for key, value in getattr(self, name).state_dict().items():
                value[critic_cut] = state[name][key]

        def load_moments(optimizer, member: dict, put) -> None:
            params = [p for group in optimizer.param_groups for p in group["params"]]
            for index, param in enumerate(params):  # the indices of optimizer.state_dict()
                if index not in member["state"]:
                    continue  # the member never stepped this parameter
                saved, live = member["state"][index], optimizer.state[param]
                if not live:  # a fresh optimizer: create its state as its first step would
                    live["step"] = saved["step"].clone().to(param.device)
                    live |= {key: torch.zeros_like(param) for key in ADAM_MOMENTS}
                for key in ADAM_MOMENTS:
                    put(live[key], saved[key].to(param.device))
                live["step"].copy_(saved["step"])

        def put_actor(live, saved):  # Linear (out, in) -> EnsembleLinear member (in, out)
            live[i] = saved.T if saved.dim() == 2 else saved

        def put_critic(live, saved):
            live[critic_cut] = saved

        load_moments(self.actor_optimizer, state["actor_optimizer"], put_actor)
        load_moments(self.critic_optimizer, state["critic_optimizer"], put_critic)
        self._load_counters(state)
        self.rngs[i].bit_generator.state = state["rng"]
        self.noises[i].load_state_dict(state["noise"])
        self.buffers[i].load_state_dict(state["buffer"])
        guard = state.get("guard", {"skipped": 0, "in_a_row": 0})  # older checkpoints: none
        self.guard.skipped[i], self.guard.in_a_row[i] = guard["skipped"], guard["in_a_row"]
        self._refill_if_lost(state["buffer"])

    def _critic_slice(self, i: int) -> slice:
        """Member ``i``'s critics in the ``K * C`` critic ensemble."""
        return slice(i * self.num_critics, (i + 1) * self.num_critics)


class MemberAgent(Agent):
    """Member ``index`` of a population seen as an agent of its own: it acts greedily
    (evaluations) and checkpoints as a single agent; the population does the learning."""

    def __init__(self, population: ActorCritic, index: int):
        self.population, self.index = population, index
        self.members = slice(index, index + 1)
        self.device = population.device

    def act(self, obs: np.ndarray, explore: bool = False) -> np.ndarray:
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            action = self.population.actor(obs_t.view(1, 1, -1), members=self.members)[0, 0]
        return action.cpu().numpy().astype(np.float32)

    def observe(self, transition: Transition) -> None:
        raise NotImplementedError("a population member observes through the population")

    def update(self) -> dict[str, torch.Tensor]:
        raise NotImplementedError("a population member learns through the population")

    def state_dict(self, with_buffer: bool = False) -> dict:
        return self.population.member_state_dict(self.index, with_buffer)

    def load_state_dict(self, state: dict) -> None:
        self.population.load_member_state_dict(self.index, state)

    def resume_notes(self) -> dict[str, str]:
        return self.population.resume_notes()
