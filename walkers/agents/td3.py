"""TD3: Twin Delayed Deep Deterministic policy gradient (Fujimoto, van Hoof, Meger 2018,
"Addressing Function Approximation Error in Actor-Critic Methods"), Algorithm 1.

The off-policy core (:class:`~walkers.agents.actor_critic.ActorCritic`) runs the loop of an
update; this module is TD3's math, in the paper's order:

    select a ~ clip(pi(s) + eps, low, high), eps ~ N(0, sigma)            (policy)
    a~ <- clip(pi'(s') + clip(eps, -c, c), low, high), eps ~ N(0, s~)      (next_value)
    y <- r + gamma (1 - d) min_{i=1,2} Q'_i(s', a~)                        (next_value)
    theta_i <- argmin N^-1 sum (y - Q_i(s, a))^2                            (the core)
    if t mod d = 0:                                                         (policy_delay)
        grad J(phi) = N^-1 sum grad_a Q_1(s, a)|a=pi(s) grad_phi pi(s)     (actor_loss)
        theta'_i <- tau theta_i + (1 - tau) theta'_i; phi' likewise         (the core)

sigma, s~, c are fractions of the action half-range; the three ideas (twin critics with the
min, target policy smoothing, delayed updates) are the class attributes and arguments below,
so DDPG (:mod:`walkers.agents.ddpg`) is this class with the three switched off.
"""

from __future__ import annotations

import numpy as np
import torch

from walkers.agents.actor_critic import ActorCritic
from walkers.agents.noise import NOISE_TYPES, GaussianNoise
from walkers.data.replay import Batch


class TD3(ActorCritic):
    """Clipped double-Q (two critics), target policy smoothing, delayed policy updates; other
    hyperparameters (``lr``, ``batch_size``, ``tau``, ...) are the core's. Each is declared, with
    its default (the paper's) and doc, in :mod:`walkers.agents.schemas`.

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

    # --- learning ------------------------------------------------------------------------------
    def update_noise(self, b: Batch) -> tuple[torch.Tensor | None, None]:
        """The target smoothing noise eps ~ N(0, 1) (None without smoothing); the actor's
        deterministic gradient needs none."""
        return (torch.randn_like(b.action) if self.policy_noise > 0 else None), None

    def next_value(self, next_obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """min_i Q'_i(s', a~), a~ = clip(pi'(s') + clip(s~ eps, -c, c), low, high) with
        eps = ``noise`` (target policy smoothing; None: a~ = pi'(s'))."""
        next_action = self.actor_target(next_obs)
        if noise is not None:
            eps = (noise * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)
            next_action = (next_action + eps * self.actor.action_scale).clamp(
                self.low_t, self.high_t
            )
        return self.min_target_q(next_obs, next_action)

    def actor_loss(self, obs: torch.Tensor, noise: None) -> tuple[torch.Tensor, None]:
        """-Q_1(s, pi(s)) per member ``(K,)``: the deterministic policy gradient on the first
        critic (the critics' weights stay fixed)."""
        q_pi = self.critic(obs, self.actor(obs), members=slice(0, None, self.num_critics))
        return -q_pi.mean(dim=-1), None
