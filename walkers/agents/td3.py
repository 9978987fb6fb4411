"""TD3: Twin Delayed Deep Deterministic policy gradient (Fujimoto, van Hoof, Meger 2018,
"Addressing Function Approximation Error in Actor-Critic Methods"), Algorithm 1.

:meth:`TD3.update` is the paper's loop body, top to bottom:

    sample a mini-batch of N transitions (s, a, r, s', d)                  (sample)
    a~ <- clip(pi'(s') + clip(eps, -c, c), low, high), eps ~ N(0, s~)      (critic_loss)
    y <- r + gamma (1 - d) min_{i=1,2} Q'_i(s', a~)                        (critic_loss)
    theta_i <- argmin N^-1 sum (y - Q_i(s, a))^2                            (a guarded step)
    if t mod d = 0:
        grad J(phi) = N^-1 sum grad_a Q_1(s, a)|a=pi(s) grad_phi pi(s)     (actor_loss)
        theta'_i <- tau theta_i + (1 - tau) theta'_i; phi' likewise         (soft_update)

and acting is a ~ clip(pi(s) + eps, low, high), eps ~ N(0, sigma) (:meth:`TD3.policy`). sigma, s~,
c are fractions of the action half-range; d is terminated only (a time limit's truncation still
bootstraps). The three ideas (twin critics with the min, target policy smoothing, delayed
updates) are the class attributes and arguments below, so DDPG (:mod:`walkers.agents.ddpg`) is
this class with the three switched off. What every off-policy agent shares (replay, ensembles,
the NaN guard, populations, checkpoints) is :mod:`walkers.agents.common.actor_critic`.
"""

from __future__ import annotations

import numpy as np
import torch

from walkers.agents.common.actor_critic import ActorCritic, frozen, logged
from walkers.agents.common.health import guarded_step
from walkers.agents.common.networks import soft_update
from walkers.agents.common.noise import NOISE_TYPES, GaussianNoise
from walkers.data.replay import Batch


class TD3(ActorCritic):
    """Clipped double-Q (two critics), target policy smoothing, delayed policy updates; other
    hyperparameters (``lr``, ``batch_size``, ``tau``, ...) are the core's. Each is declared, with
    its default (the paper's) and doc, in :mod:`walkers.agents.declarations.schemas`.

    ``policy_noise``/``noise_clip`` (smoothing) and ``policy_delay`` are required while the class
    uses the idea; a subclass that turns it off (DDPG) takes none."""

    num_critics = 2  # clipped double-Q: the target takes the min of the twins
    target_smoothing = True  # clipped noise on the target action
    delayed_updates = True  # the actor and the targets move every policy_delay critic updates

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        exploration_noise: float,
        noise_type: str | None = None,
        policy_noise: float | None = None,
        noise_clip: float | None = None,
        policy_delay: int | None = None,
        **core,
    ):
        smoothing = {"policy_noise": policy_noise, "noise_clip": noise_clip}
        self._require(smoothing, self.target_smoothing)
        self._require({"policy_delay": policy_delay}, self.delayed_updates)
        self.policy_noise = policy_noise if self.target_smoothing else 0.0
        self.noise_clip = noise_clip if self.target_smoothing else 0.0
        self.policy_delay = policy_delay if self.delayed_updates else 1
        # TD3 explores with the paper's Gaussian noise; DDPG declares noise_type (gaussian | ou)
        self.exploration_sigma, self.noise_type = exploration_noise, noise_type or "gaussian"
        super().__init__(obs_dim, action_low, action_high, **core)
        self.actor_target, self.critic_target = (
            self.target_of(self.actor),
            self.target_of(self.critic),
        )
        # exploration and smoothing noise are fractions of the action half-range
        self.noise_scale = (self.action_high - self.action_low) / 2

    def _require(self, knobs: dict, idea_used: bool) -> None:
        """The knobs of an idea are given exactly when the class uses the idea."""
        name = type(self).__name__
        for knob, value in knobs.items():
            if idea_used and value is None:
                raise TypeError(f"{name}.__init__() needs {knob}")
            if not idea_used and value is not None:
                raise TypeError(
                    f"{name}.__init__() got an unexpected keyword argument {knob!r} "
                    f"({name} turns that idea of TD3 off)"
                )

    # --- acting: a ~ clip(pi(s) + eps, low, high) ------------------------------------------------
    def exploration_noise(self, rng: np.random.Generator, act_dim: int) -> GaussianNoise:
        return NOISE_TYPES[self.noise_type](self.exploration_sigma, act_dim, rng)

    def policy(self, obs: torch.Tensor, noise: np.ndarray | None) -> np.ndarray:
        """pi(s), plus the exploration noise when exploring, clipped to the bounds."""
        actions = self.actor(obs)[:, 0].cpu().numpy()
        if noise is not None:
            actions = np.clip(actions + noise * self.noise_scale, self.action_low, self.action_high)
        return actions.astype(np.float32)

    # --- learning: Algorithm 1's loop body ----------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if not self.begin_update():
            return {}
        b = self.sample()
        smoothing_noise, _ = self.update_noise(b)
        critic_loss, q_mean = self.critic_loss(b, smoothing_noise)
        critic_bad = guarded_step(self.critic_optimizer, critic_loss, self.num_critics)
        metrics = {"loss/critic": logged(critic_loss), "train/q_mean": logged(q_mean)}
        actor_bad = None  # the delayed step's verdict, when it runs
        if self.num_updates % self.policy_delay == 0:
            with frozen(self.critic):
                actor_loss = self.actor_loss(b)
            # critic_bad, not the critic loss: under CUDA graphs the actor-loss run has already
            # reclaimed the critic-loss run's outputs
            actor_bad = guarded_step(self.actor_optimizer, actor_loss, 1, also_bad=critic_bad)
            soft_update(self.critic_target, self.critic, self.tau)
            soft_update(self.actor_target, self.actor, self.tau)
            metrics["loss/actor"] = logged(actor_loss)
        return metrics | self.record_health(critic_bad, delayed_bad=actor_bad)

    def update_noise(self, b: Batch) -> tuple[torch.Tensor | None, None]:
        """The target smoothing noise eps ~ N(0, 1) (None without smoothing); the actor's
        deterministic gradient needs none."""
        return (torch.randn_like(b.action) if self.policy_noise > 0 else None), None

    def critic_loss(
        self, b: Batch, smoothing_noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per member ``(K,)``: sum_i N^-1 sum (y - Q_i(s, a))^2 with the target
        y = r + gamma (1 - terminated) min_i Q'_i(s', a~), a~ = clip(pi'(s') + clip(s~ eps, -c,
        c), low, high), eps = ``smoothing_noise`` (None: a~ = pi'(s')); and mean Q ``(K,)``."""
        with torch.no_grad():
            next_action = self.actor_target(b.next_obs)
            if smoothing_noise is not None:
                eps = (smoothing_noise * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)
                next_action = (next_action + eps * self.actor.action_scale).clamp(
                    self.low_t, self.high_t
                )
            next_q = self.q_values(self.critic_target, b.next_obs, next_action).min(dim=1).values
            y = b.reward + self.gamma * (1.0 - b.terminated) * next_q
        q = self.q_values(self.critic, b.obs, b.action)
        return self.critics_regression(q, y), q.detach().mean(dim=(1, 2))

    def actor_loss(self, b: Batch) -> torch.Tensor:
        """-Q_1(s, pi(s)) per member ``(K,)``: the deterministic policy gradient on the first
        critic alone (of the batch, TD3 reads only the states)."""
        _, q_pi = self.policy_q1(b.obs)
        return -q_pi.mean(dim=-1)

    def policy_q1(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pi(s) ``(K, N, act_dim)`` and Q_1(s, pi(s)) ``(K, N)``: each member's first critic."""
        action = self.actor(obs)
        return action, self.critic(obs, action, members=slice(0, None, self.num_critics))

    # --- checkpoints: the targets are per-member parts too ---------------------------------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        cuts = super().member_cuts(i)
        return cuts | {"actor_target": cuts["actor"], "critic_target": cuts["critic"]}
