"""SAC: Soft Actor-Critic with automatic entropy tuning (Haarnoja et al. 2018, "Soft Actor-Critic
Algorithms and Applications", the "v2" paper's Algorithm 1).

:class:`SoftActorCritic` holds what SAC and CrossQ (:mod:`walkers.agents.crossq`) share, the
maximum-entropy parts:

- the actor is a squashed Gaussian, a = tanh(mu(s) + sigma(s) * eps) scaled onto the bounds,
  eps ~ N(0, I) (:class:`~walkers.agents.common.networks.EnsembleGaussianActor`);
- the temperature alpha, learned on log alpha (the reference implementations' parameterization)
  with its own Adam: J(alpha) = E[-alpha (log pi(a|s) + H_target)], H_target = -|A|;
- exploration samples the policy itself (eps from each member's exploration stream; uniform random
  actions during the ``learning_starts`` warm-up, as TD3); evaluation acts with tanh(mu(s)).

:meth:`SAC.update` is the paper's loop body, every gradient step:

- soft Bellman target y = r + gamma (1 - d) (min_j Q'_j(s', a') - alpha log pi(a'|s')),
  a' ~ pi(.|s') sampled from the current policy (no target actor), d = terminated;
- the critics' step, then the actor's on J_pi = E_s,eps[alpha log pi(a|s) - min_j Q_j(s, a)]
  with a reparameterized, then the temperature's, then the target critics' soft update.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from walkers.agents.common.actor_critic import ActorCritic, GaussianNoise, frozen, logged
from walkers.agents.common.functional import gradient_of, guarded_adam_step
from walkers.agents.common.health import skip_nonfinite
from walkers.agents.common.networks import EnsembleGaussianActor, Temperature, soft_update
from walkers.data.replay import Batch


class SoftActorCritic(ActorCritic):
    """The maximum-entropy actor-critic SAC and CrossQ share: the squashed Gaussian actor's
    exploration, the temperature (:meth:`build_temperature`) and its loss. The networks and the
    update are each algorithm's own."""

    num_critics = 2  # clipped double-Q

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
        self.alpha_lr, self.alpha_init = alpha_lr or lr, alpha_init
        self.target_entropy = (
            -float(self.act_dim) if target_entropy is None else float(target_entropy)
        )

    def build_temperature(self) -> None:
        """alpha of every member and its own Adam (Adam's own betas, as the references)."""
        self.temperature = Temperature(self.population, self.alpha_init).to(self.device)
        self.alpha_optimizer = self.adam(self.temperature, self.alpha_lr, betas=(0.9, 0.999))

    # --- acting ---------------------------------------------------------------------------------
    def exploration_noise(self, rng: np.random.Generator) -> GaussianNoise:
        """The eps ~ N(0, I) of a member's policy sample, from its own exploration stream
        (walkers.seeding): a soft actor-critic explores by sampling its policy, with no added
        noise."""
        return GaussianNoise(1.0, self.act_dim, rng)

    def policy(self, obs: torch.Tensor, noise: np.ndarray | None) -> np.ndarray:
        """A sample of pi(.|s) with eps = ``noise`` (exploring), else tanh(mu(s)) (greedy)."""
        if noise is None:
            return self.actor(obs)[:, 0].cpu().numpy()
        eps = torch.as_tensor(noise, dtype=torch.float32, device=self.device).unsqueeze(1)
        action, _ = self.actor.sample(obs, eps)
        return action[:, 0].cpu().numpy()

    # --- learning: the temperature's loss, which both updates use --------------------------------
    def temperature_loss(self, log_pi: torch.Tensor) -> torch.Tensor:
        """J(alpha) = E[-log alpha (log pi(a|s) + H_target)] per member ``(K,)``, the log pi
        treated as constants. Its gradient -(log pi + H_target) is positive when the entropy
        -log pi is above the target, so alpha falls; below it, alpha rises."""
        log_alpha = self.temperature.log_alpha.unsqueeze(-1)
        return -(log_alpha * (log_pi + self.target_entropy).detach()).mean(dim=-1)

    @staticmethod
    def entropy_metrics(alpha_loss, alpha, log_pi) -> dict[str, torch.Tensor]:
        """The temperature step's metrics: its loss, alpha after it, the samples' entropy."""
        return {
            "loss/alpha": alpha_loss.detach(),
            "train/alpha": alpha,
            "train/entropy": -log_pi.mean(dim=-1),
        }

    # --- checkpoints: the temperature is a per-member part too -----------------------------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        own = self.own_slice(i)
        return super().member_cuts(i) | {"temperature": own, "alpha_optimizer": own}


class SAC(SoftActorCritic):
    """Soft Actor-Critic v2: twin critics with target copies, no target actor; hyperparameters
    declared in :mod:`walkers.agents.declarations.schemas`."""

    def __init__(self, obs_dim, action_low, action_high, **hyperparameters):
        super().__init__(obs_dim, action_low, action_high, **hyperparameters)
        self.actor = self.build_actor(EnsembleGaussianActor)  # pi_phi
        self.critic = self.build_critic()  # Q_theta_1, Q_theta_2 of every member
        self.critic_target = self.target_of(self.critic)  # theta'_1, theta'_2 (no target actor)
        self.actor_optimizer = self.adam(self.actor, self.actor_lr)
        self.critic_optimizer = self.adam(self.critic, self.critic_lr)
        self.build_temperature()
        self.members = self.build_members(self.exploration_noise)
        self.compile_update()

    # --- learning: Algorithm 1's loop body (one gradient step) -----------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if not self.begin_update():
            return {}
        b = self.sample()
        next_eps = self.noise_like(b.action)  # a' ~ pi(.|s'), for the target
        eps = self.noise_like(b.action)  # a ~ pi(.|s), for the actor's loss
        if self.compiled_steps is not None:  # compile=true on the CPU: the steps below, whole
            return self.compiled_steps(b, next_eps, eps)

        critic_loss, q_mean = self.critic_loss(b, next_eps)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.sum().backward()
        critic_skipped = skip_nonfinite(self.critic_optimizer, critic_loss, self.num_critics)
        self.critic_optimizer.step()

        with frozen(self.critic):
            actor_loss, log_pi = self.actor_loss(b.obs, eps)
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.sum().backward()
        actor_skipped = skip_nonfinite(self.actor_optimizer, actor_loss, also_skip=critic_skipped)
        self.actor_optimizer.step()

        alpha_loss = self.temperature_loss(log_pi)
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.sum().backward()
        skip_nonfinite(self.alpha_optimizer, alpha_loss, also_skip=actor_skipped)
        self.alpha_optimizer.step()

        return self.soft_update_and_metrics(
            critic_loss, q_mean, actor_loss, alpha_loss, log_pi, critic_skipped, actor_skipped
        )

    def functional_steps(
        self, b: Batch, next_eps: torch.Tensor, eps: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """:meth:`update`'s steps after its draws, functional (``compile=true`` on the CPU)."""
        grads, (critic_loss, q_mean) = self.critic_gradient(b, next_eps)
        critic_skipped = guarded_adam_step(
            self.critic_optimizer, grads, critic_loss, self.num_critics
        )
        grads, (actor_loss, log_pi) = self.actor_gradient(b.obs, eps)
        actor_skipped = guarded_adam_step(
            self.actor_optimizer, grads, actor_loss, also_skip=critic_skipped
        )
        grads, (alpha_loss,) = self.temperature_gradient(log_pi)
        guarded_adam_step(self.alpha_optimizer, grads, alpha_loss, also_skip=actor_skipped)

        return self.soft_update_and_metrics(
            critic_loss, q_mean, actor_loss, alpha_loss, log_pi, critic_skipped, actor_skipped
        )

    def soft_update_and_metrics(
        self, critic_loss, q_mean, actor_loss, alpha_loss, log_pi, critic_skipped, actor_skipped
    ) -> dict[str, torch.Tensor]:
        """The update's last step, the target critics' soft update, and its metrics."""
        soft_update(self.critic_target, self.critic, self.tau)
        metrics = {
            "loss/critic": logged(critic_loss),
            "train/q_mean": logged(q_mean),
            "loss/actor": logged(actor_loss),
            **self.entropy_metrics(alpha_loss, self.temperature(), log_pi),
        }
        return metrics | self.record_health(critic_skipped, delayed_bad=actor_skipped)

    def functional_gradients(self) -> dict[str, Callable]:
        return {
            "critic_gradient": gradient_of(self.critic, self.critic_loss),
            "actor_gradient": gradient_of(self.actor, self.actor_loss),
            "temperature_gradient": gradient_of(
                self.temperature, lambda log_pi: (self.temperature_loss(log_pi),)
            ),
        }

    def critic_loss(self, b: Batch, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per member ``(K,)``: J_Q = 1/2 sum_j N^-1 sum (y - Q_j(s, a))^2 with the soft target
        y = r + gamma (1 - terminated) (min_j Q'_j(s', a') - alpha log pi(a'|s')),
        a' ~ pi(.|s') with eps = ``noise``; and mean Q ``(K,)``."""
        with torch.no_grad():
            next_action, next_log_pi = self.actor.sample(b.next_obs, noise)
            next_q = self.q_values(self.critic_target, b.next_obs, next_action).min(dim=1).values
            alpha = self.temperature().unsqueeze(-1)
            y = b.reward + self.gamma * (1.0 - b.terminated) * (next_q - alpha * next_log_pi)
        q = self.q_values(self.critic, b.obs, b.action)
        return 0.5 * self.critics_regression(q, y), q.detach().mean(dim=(1, 2))

    def actor_loss(
        self, obs: torch.Tensor, noise: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """J_pi = E[alpha log pi(a|s) - min_j Q_j(s, a)] per member ``(K,)``, a = tanh(mu +
        sigma * eps) reparameterized so the gradient flows through the action into the critics
        (whose weights stay fixed); and log pi(a|s) ``(K, N)`` for the temperature step."""
        action, log_pi = self.actor.sample(obs, noise)
        min_q = self.q_values(self.critic, obs, action).min(dim=1).values
        alpha = self.temperature().unsqueeze(-1)
        return (alpha * log_pi - min_q).mean(dim=-1), log_pi.detach()

    def member_cuts(self, i: int) -> dict[str, slice]:
        cuts = super().member_cuts(i)
        return cuts | {"critic_target": cuts["critic"]}
