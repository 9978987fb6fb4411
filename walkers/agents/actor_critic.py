"""Deterministic off-policy actor-critic with experience replay: the core of DDPG and TD3.

TD3 (Fujimoto et al. 2018) is this core with ``num_critics=2`` (clipped double-Q),
``policy_noise > 0`` (target policy smoothing) and ``policy_delay=2`` (delayed actor and target
updates). DDPG as the TD3 paper's "our DDPG" is the same core with one critic, no smoothing and
no delay. The update in :meth:`ActorCritic.update` follows Algorithm 1 of the TD3 paper line by
line.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np
import torch
from torch.nn import functional as F

from walkers.agents.base import Agent, Transition, resolve_device
from walkers.agents.health import NonFiniteGuard
from walkers.buffers import ReplayBuffer
from walkers.nn import Actor, make_critic, soft_update


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
        self.rng = np.random.default_rng(seed)
        half_range = (self.action_high - self.action_low) / 2
        self.noise = NOISE_TYPES[noise_type](exploration_noise, act_dim, self.rng)
        self.noise_scale = half_range  # noise std is given as a fraction of the half-range

        torch.manual_seed(seed)
        self.actor = Actor(obs_dim, act_dim, hidden_sizes, action_low, action_high).to(self.device)
        critic_hidden = hidden_sizes if critic_hidden_sizes is None else critic_hidden_sizes
        self.critic = make_critic(
            critic_architecture, obs_dim, act_dim, critic_hidden, num_critics
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

        self.buffer = ReplayBuffer(buffer_size, obs_dim, act_dim, self.device, seed=seed)
        self.steps = 0  # transitions observed
        self.num_updates = 0  # critic updates done
        self.guard = NonFiniteGuard(self.device)

    # --- acting -------------------------------------------------------------------------------
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        if explore and self.steps < self.learning_starts:  # uniform random warm-up
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

    # --- learning -----------------------------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if self.steps < self.learning_starts or len(self.buffer) < self.batch_size:
            return {}
        self.num_updates += 1
        b = self.buffer.sample(self.batch_size)

        # Critic: regress every Q_i onto y = r + gamma * (1 - terminated) * min_j Q'_j(s', a~),
        # a~ = clip(pi'(s') + clip(eps, -c, c), low, high), eps ~ N(0, sigma)   (smoothing)
        with torch.no_grad():
            next_action = self.actor_target(b.next_obs)
            if self.policy_noise > 0:
                eps = torch.randn_like(next_action) * self.policy_noise
                eps = eps.clamp(-self.noise_clip, self.noise_clip) * self.actor.action_scale
                next_action = (next_action + eps).clamp(self.low_t, self.high_t)
            next_q = self.critic_target(b.next_obs, next_action).min(dim=0).values
            target = b.reward + self.gamma * (1.0 - b.terminated) * next_q
        q = self.critic(b.obs, b.action)  # (num_critics, batch)
        critic_loss = F.mse_loss(q, target.expand_as(q), reduction="none").mean(dim=1).sum()
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        # NaN/inf guard without a host sync: fused Adam skips its step when found_inf is 1.
        bad = self.guard.is_bad(critic_loss)
        self.critic_optimizer.found_inf = bad
        self.critic_optimizer.step()
        self.guard.record(bad)
        metrics = {"loss/critic": critic_loss.detach(), "train/q_mean": q.detach().mean()}

        # Delayed policy update: maximize Q_1(s, pi(s)), then move the targets.
        if self.num_updates % self.policy_delay == 0:
            actor_loss = -self.critic(b.obs, self.actor(b.obs), members=slice(0, 1)).mean()
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.backward(inputs=list(self.actor.parameters()))  # no critic weight grads
            self.actor_optimizer.found_inf = self.guard.is_bad(critic_loss, actor_loss)
            self.actor_optimizer.step()
            soft_update(self.critic_target, self.critic, self.tau)
            soft_update(self.actor_target, self.actor, self.tau)
            metrics["loss/actor"] = actor_loss.detach()
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
        self.steps, self.num_updates = state["steps"], state["num_updates"]
        self.rng.bit_generator.state = state["rng"]
        self.noise.load_state_dict(state["noise"])
        self.buffer.load_state_dict(state["buffer"])
        if "guard" in state:
            self.guard.load_state_dict(state["guard"])
