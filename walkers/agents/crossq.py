"""CrossQ (Bhatt, Palenicek et al., ICLR 2024, "CrossQ: Batch Normalization in Deep Reinforcement
Learning for Greater Sample Efficiency and Simplicity"), as sb3-contrib's CrossQ defines it.

SAC (:mod:`walkers.agents.sac`: the squashed Gaussian actor, the temperature, exploration by the
policy's samples) with three changes:

- no target networks: the target bootstraps from the live critics;
- Batch Renormalization before every linear layer of the critics and the actor
  (:mod:`walkers.agents.common.renorm`), and wide critics (2048 units in the paper);
- one joint forward pass of the critics over (s, a) and (s', a'), a' ~ pi(.|s'), so the batch
  statistics are those of the mixture of both: the target comes out of the same pass, under
  stop-gradient. Evaluated apart, (s', a') would look out of distribution to the normalization.

:meth:`CrossQ.update`, every gradient step:

    a', log pi(a'|s') <- pi(.|s')                 (the actor's running statistics)
    Q(s, a), Q(s', a') <- one pass over [(s, a); (s', a')]   (batch statistics, which move)
    y <- r + gamma (1 - d) (min_j sg(Q_j(s', a')) - alpha log pi(a'|s'))
    theta <- argmin 1/2 sum_j N^-1 sum (y - Q_j(s, a))^2
    every policy_delay updates:
        a, log pi(a|s) <- pi(.|s)                  (batch statistics, which move)
        alpha's step on J(alpha) = E[-alpha (log pi(a|s) + H_target)]
        phi's step on J_pi = E[alpha log pi(a|s) - min_j Q_j(s, a)]   (critics' running stats)

alpha is the update's own, read before its step, in the target and the actor loss. The networks
stay in the normalization's inference mode (running statistics) except inside the passes above,
so acting and evaluation use running statistics; those are part of checkpoints (module buffers,
a slice per population member).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from walkers.agents.common.actor_critic import frozen, logged
from walkers.agents.common.health import skip_nonfinite
from walkers.agents.common.renorm import RenormCriticEnsemble, RenormGaussianActor, batch_statistics
from walkers.agents.sac import SoftActorCritic
from walkers.data.replay import Batch


class CrossQ(SoftActorCritic):
    """CrossQ; hyperparameters (the paper's, declared in :mod:`walkers.agents.declarations.schemas`)
    are the core's and SAC's temperature's, plus the actor's delay, the critics' widths and the
    renormalization's ``renorm_momentum`` and ``renorm_warmup_steps``."""

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        policy_delay: int,
        renorm_momentum: float,
        renorm_warmup_steps: int,
        critic_hidden_sizes: Sequence[int],
        adam_betas: Sequence[float],
        **hyperparameters,
    ):
        super().__init__(
            obs_dim,
            action_low,
            action_high,
            critic_hidden_sizes=critic_hidden_sizes,
            adam_betas=adam_betas,
            **hyperparameters,
        )
        self.policy_delay = policy_delay
        renorm = {"momentum": renorm_momentum, "warmup_steps": renorm_warmup_steps}
        self.actor = self.build_actor(RenormGaussianActor, **renorm)  # pi_phi
        self.critic = self.build_critic(RenormCriticEnsemble, **renorm)  # Q_1, Q_2; no targets
        self.actor_optimizer = self.adam(self.actor, self.actor_lr)
        self.critic_optimizer = self.adam(self.critic, self.critic_lr)
        self.build_temperature()
        self.members = self.build_members(self.exploration_noise)
        self.compile_update()

    @property
    def update_period(self) -> int:
        """The delayed steps (actor, temperature) run every ``policy_delay``-th update."""
        return self.policy_delay

    # --- learning ---------------------------------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if not self.begin_update():
            return {}
        b = self.sample()
        next_eps = self.noise_like(b.action)  # a' ~ pi(.|s'), for the target
        eps = self.noise_like(b.action)  # a ~ pi(.|s), for the delayed steps
        alpha = self.temperature().unsqueeze(-1)  # this update's, before the temperature's step

        with batch_statistics(self.critic):  # the joint pass's statistics, which move
            critic_loss, q_mean = self.critic_loss(b, next_eps, alpha)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.sum().backward()
        critic_skipped = skip_nonfinite(self.critic_optimizer, critic_loss, self.num_critics)
        self.critic_optimizer.step()
        metrics = {"loss/critic": logged(critic_loss), "train/q_mean": logged(q_mean)}

        actor_skipped = None  # the delayed step's verdict, when it runs
        if self.num_updates % self.policy_delay == 0:
            with batch_statistics(self.actor):  # the batch of s's statistics, which move
                action, log_pi = self.actor.sample(b.obs, eps)

            alpha_loss = self.temperature_loss(log_pi.detach())
            self.alpha_optimizer.zero_grad(set_to_none=True)
            alpha_loss.sum().backward()
            skip_nonfinite(self.alpha_optimizer, alpha_loss, also_skip=critic_skipped)
            self.alpha_optimizer.step()
            metrics |= self.entropy_metrics(alpha_loss, self.temperature(), log_pi.detach())

            with frozen(self.critic):
                actor_loss = self.actor_loss(b.obs, action, log_pi, alpha)
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.sum().backward()
            actor_skipped = skip_nonfinite(
                self.actor_optimizer, actor_loss, also_skip=critic_skipped
            )
            self.actor_optimizer.step()
            metrics["loss/actor"] = logged(actor_loss)
        return metrics | self.record_health(critic_skipped, delayed_bad=actor_skipped)

    def critic_loss(
        self, b: Batch, noise: torch.Tensor, alpha: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per member ``(K,)``: 1/2 sum_j N^-1 sum (y - Q_j(s, a))^2, Q(s, a) and the target's
        Q(s', a') from one joint pass (in the critics' batch statistics: :meth:`update`), a' ~
        pi(.|s') from the actor in running statistics; and mean Q ``(K,)``."""
        n = b.obs.shape[1]
        with torch.no_grad():
            next_action, next_log_pi = self.actor.sample(b.next_obs, noise)
        q_joint = self.q_values(
            self.critic,
            torch.cat([b.obs, b.next_obs], dim=1),
            torch.cat([b.action, next_action], dim=1),
        )
        q, next_q = q_joint.split(n, dim=2)
        with torch.no_grad():  # stop-gradient: the target is a constant of the critics' step
            soft_value = next_q.min(dim=1).values - alpha * next_log_pi
            y = b.reward + self.gamma * (1.0 - b.terminated) * soft_value
        return 0.5 * self.critics_regression(q, y), q.detach().mean(dim=(1, 2))

    def actor_loss(
        self, obs: torch.Tensor, action: torch.Tensor, log_pi: torch.Tensor, alpha: torch.Tensor
    ) -> torch.Tensor:
        """J_pi = E[alpha log pi(a|s) - min_j Q_j(s, a)] per member ``(K,)``, the critics in
        running statistics."""
        min_q = self.q_values(self.critic, obs, action).min(dim=1).values
        return (alpha * log_pi - min_q).mean(dim=-1)
