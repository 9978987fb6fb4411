"""SAC: Soft Actor-Critic with automatic entropy tuning (Haarnoja et al. 2018, "Soft Actor-Critic
Algorithms and Applications", the "v2" paper's Algorithm 1).

The off-policy core (:class:`~walkers.agents.actor_critic.ActorCritic`: replay, the critics as
one ensemble and the min over a member's target critics, soft target updates, the NaN guard,
populations, checkpoints, ``compile``) runs the loop of an update; this module is SAC's math:

- the actor is a squashed Gaussian, a = tanh(mu(s) + sigma(s) * eps) scaled onto the bounds,
  eps ~ N(0, I) (:class:`~walkers.agents.networks.EnsembleGaussianActor`); no target actor;
- soft Bellman target: y = r + gamma (1 - d) (min_j Q'_j(s', a') - alpha log pi(a'|s')),
  a' ~ pi(.|s') sampled from the current policy;
- actor loss J_pi = E_s,eps[alpha log pi(a|s) - min_j Q_j(s, a)], a reparameterized;
- temperature loss J(alpha) = E[-alpha (log pi(a|s) + H_target)] with H_target = -|A|, taken on
  log alpha (the reference implementations' parameterization) with its own Adam;
- every update: critics, actor, temperature, then the critics' soft target update.

Exploration samples the policy itself (eps from each member's exploration stream; uniform random
actions during the ``learning_starts`` warm-up, as TD3); evaluation acts with tanh(mu(s)).
"""

from __future__ import annotations

import numpy as np
import torch

from walkers.agents.actor_critic import ActorCritic
from walkers.agents.health import guarded_step
from walkers.agents.networks import EnsembleGaussianActor, Temperature
from walkers.agents.noise import GaussianNoise
from walkers.data.replay import Batch


class SAC(ActorCritic):
    """Soft Actor-Critic; hyperparameters are the core's (``lr``, ``batch_size``, ``tau``, ...)
    plus the temperature's, declared in :mod:`walkers.agents.schemas`."""

    actor_class = EnsembleGaussianActor
    uses_actor_target = False  # the reference SAC (v2) has none: a' is sampled from pi itself
    num_critics = 2  # clipped double-Q
    policy_delay = 1  # actor and temperature at every update

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        lr: float,
        alpha_lr: float | None,
        alpha_init: float,
        target_entropy: float | None,
        **hyperparameters,
    ):
        super().__init__(obs_dim, action_low, action_high, lr=lr, **hyperparameters)
        act_dim = len(self.action_low)
        self.target_entropy = -float(act_dim) if target_entropy is None else float(target_entropy)
        self.temperature = Temperature(self.population, alpha_init).to(self.device)
        self.alpha_optimizer = torch.optim.Adam(
            self.temperature.parameters(), lr=alpha_lr or lr, fused=True
        )

    # --- acting ---------------------------------------------------------------------------------
    def exploration_noise(self, rng: np.random.Generator, act_dim: int) -> GaussianNoise:
        """The eps ~ N(0, I) of a member's policy sample, from its own exploration stream
        (walkers.seeding): SAC explores by sampling its policy, with no added noise."""
        return GaussianNoise(1.0, act_dim, rng)

    def policy(self, obs: torch.Tensor, noise: np.ndarray | None) -> np.ndarray:
        """A sample of pi(.|s) with eps = ``noise`` (exploring), else tanh(mu(s)) (greedy)."""
        if noise is None:
            return self.actor(obs)[:, 0].cpu().numpy()
        eps = torch.as_tensor(noise, dtype=torch.float32, device=self.device).unsqueeze(1)
        action, _ = self.actor.sample(obs, eps)
        return action[:, 0].cpu().numpy()

    # --- learning (SAC v2 paper, Algorithm 1) -----------------------------------------------------
    def update_noise(self, b: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """eps ~ N(0, I) for a' ~ pi(.|s') (the critic target) and a ~ pi(.|s) (the actor loss)."""
        return torch.randn_like(b.action), torch.randn_like(b.action)

    def next_value(self, next_obs: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The soft value V'(s') = min_j Q'_j(s', a') - alpha log pi(a'|s'), a' ~ pi(.|s')."""
        next_action, next_log_pi = self.actor.sample(next_obs, noise)
        alpha = self.temperature().unsqueeze(-1)
        return self.min_target_q(next_obs, next_action) - alpha * next_log_pi

    def actor_loss(
        self, obs: torch.Tensor, noise: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """J_pi = E[alpha log pi(a|s) - min_j Q_j(s, a)] per member ``(K,)``, a = tanh(mu +
        sigma * eps) reparameterized so the gradient flows through the action into the critics
        (whose weights stay fixed); and log pi(a|s) ``(K, N)`` for the temperature step."""
        action, log_pi = self.actor.sample(obs, noise)
        K, C = self.population, self.num_critics
        q = self.critic(self._per_critic(obs), self._per_critic(action)).unflatten(0, (K, C))
        min_q = q.min(dim=1).values
        alpha = self.temperature().unsqueeze(-1)
        return (alpha * log_pi - min_q).mean(dim=-1), log_pi.detach()

    def after_actor_step(self, log_pi: torch.Tensor, skip: torch.Tensor) -> dict:
        """The temperature step: J(alpha) = E[-log alpha (log pi(a|s) + H_target)] per member,
        log pi from the actor loss's sample. Its gradient -(log pi + H_target) is positive when
        the entropy -log pi is above the target, so alpha falls; below it, alpha rises."""
        alpha_loss = self.temperature_loss(log_pi)
        guarded_step(self.alpha_optimizer, alpha_loss, 1, also_bad=skip)
        return {
            "loss/alpha": alpha_loss.detach(),
            "train/alpha": self.temperature(),
            "train/entropy": -log_pi.mean(dim=-1),
        }

    def temperature_loss(self, log_pi: torch.Tensor) -> torch.Tensor:
        """J(alpha) ``(K,)`` for the samples' log pi(a|s) ``(K, N)`` (treated as constants)."""
        log_alpha = self.temperature.log_alpha.unsqueeze(-1)
        return -(log_alpha * (log_pi + self.target_entropy).detach()).mean(dim=-1)

    # --- checkpoints: the temperature is a per-member part too -----------------------------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        own = slice(i, i + 1)
        return super().member_cuts(i) | {"temperature": own, "alpha_optimizer": own}
