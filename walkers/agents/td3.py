"""TD3: Twin Delayed Deep Deterministic policy gradient (Fujimoto, van Hoof, Meger 2018,
"Addressing Function Approximation Error in Actor-Critic Methods"), Algorithm 1.

:meth:`TD3.update` is the paper's loop body, top to bottom:

    sample a mini-batch of N transitions (s, a, r, s', d)                  (sample)
    a~ <- clip(pi'(s') + clip(eps, -c, c), low, high), eps ~ N(0, s~)      (critic_loss)
    y <- r + gamma (1 - d) min_{i=1,2} Q'_i(s', a~)                        (critic_loss)
    theta_i <- argmin N^-1 sum (y - Q_i(s, a))^2                            (the critics' step)
    if t mod d = 0:
        grad J(phi) = N^-1 sum grad_a Q_1(s, a)|a=pi(s) grad_phi pi(s)     (actor_loss, its step)
        theta'_i <- tau theta_i + (1 - tau) theta'_i; phi' likewise         (soft_update)

and acting is a ~ clip(pi(s) + eps, low, high), eps ~ N(0, sigma) (:meth:`TD3.policy`). sigma, s~,
c are fractions of the action half-range; d is terminated only (a time limit's truncation still
bootstraps). Each optimizer step is written out (zero_grad, backward, step), with the NaN guard
between backward and step (:func:`~walkers.agents.common.health.skip_nonfinite`: on the device,
no host sync). The three ideas (twin critics with the min, target policy smoothing, delayed
updates) are the class attributes and arguments below, so DDPG (:mod:`walkers.agents.ddpg`) is
this class with the three switched off. What every off-policy agent shares (replay, ensembles,
the NaN guard, populations, checkpoints) is :mod:`walkers.agents.common.actor_critic`.

``compile=true`` on the CPU runs the same steps as :meth:`TD3.functional_steps`: the gradients
of the same loss methods by :func:`torch.func.grad`, Adam and the guard as tensor ops, compiled
whole (:mod:`walkers.agents.common.functional`; the same math, rounded otherwise: its own arm).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from walkers.agents.common.actor_critic import (
    NOISE_TYPES,
    ActorCritic,
    GaussianNoise,
    frozen,
    logged,
)
from walkers.agents.common.functional import gradient_of, guarded_adam_step
from walkers.agents.common.health import skip_nonfinite
from walkers.agents.common.networks import soft_update
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
        self._require(
            {"policy_noise": policy_noise, "noise_clip": noise_clip}, self.target_smoothing
        )
        self._require({"policy_delay": policy_delay}, self.delayed_updates)
        super().__init__(obs_dim, action_low, action_high, **core)
        self.policy_noise = policy_noise if self.target_smoothing else 0.0
        self.noise_clip = noise_clip if self.target_smoothing else 0.0
        self.policy_delay = policy_delay if self.delayed_updates else 1
        # TD3 explores with the paper's Gaussian noise; DDPG declares noise_type (gaussian | ou)
        self.exploration_sigma, self.noise_type = exploration_noise, noise_type or "gaussian"
        # exploration and smoothing noise are fractions of the action half-range
        self.noise_scale = (self.action_high - self.action_low) / 2

        self.actor = self.build_actor()  # pi_phi
        self.critic = self.build_critic()  # Q_theta_1, Q_theta_2 of every member
        self.actor_target = self.target_of(self.actor)  # phi'
        self.critic_target = self.target_of(self.critic)  # theta'_1, theta'_2
        self.actor_optimizer = self.adam(self.actor, self.actor_lr)
        self.critic_optimizer = self.adam(self.critic, self.critic_lr)
        self.members = self.build_members(self.exploration_noise)
        self.compile_update()

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

    @property
    def update_period(self) -> int:
        """The delayed step runs every ``policy_delay``-th update."""
        return self.policy_delay

    # --- acting: a ~ clip(pi(s) + eps, low, high) ------------------------------------------------
    def exploration_noise(self, rng: np.random.Generator) -> GaussianNoise:
        """A member's exploration noise process, drawing from its exploration stream ``rng``."""
        return NOISE_TYPES[self.noise_type](self.exploration_sigma, self.act_dim, rng)

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
        # the target smoothing noise eps ~ N(0, 1) (DDPG: none)
        smoothing_noise = self.noise_like(b.action) if self.policy_noise > 0 else None
        delayed = self.num_updates % self.policy_delay == 0
        if self.compiled_steps is not None:  # compile=true on the CPU: the steps below, whole
            return self.compiled_steps(b, smoothing_noise, delayed)

        critic_loss, q_mean = self.critic_loss(b, smoothing_noise)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.sum().backward()
        critic_skipped = skip_nonfinite(self.critic_optimizer, critic_loss, self.num_critics)
        self.critic_optimizer.step()
        metrics = {"loss/critic": logged(critic_loss), "train/q_mean": logged(q_mean)}

        actor_skipped = None  # the delayed step's verdict, when it runs
        if delayed:
            with frozen(self.critic):
                actor_loss = self.actor_loss(b)
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.sum().backward()
            # critic_skipped, not the critic loss: under CUDA graphs the actor-loss run has
            # already reclaimed the critic-loss run's outputs
            actor_skipped = skip_nonfinite(
                self.actor_optimizer, actor_loss, also_skip=critic_skipped
            )
            self.actor_optimizer.step()
            soft_update(self.critic_target, self.critic, self.tau)
            soft_update(self.actor_target, self.actor, self.tau)
            metrics["loss/actor"] = logged(actor_loss)
        return metrics | self.record_health(critic_skipped, delayed_bad=actor_skipped)

    def functional_steps(
        self, b: Batch, smoothing_noise: torch.Tensor | None, delayed: bool
    ) -> dict[str, torch.Tensor]:
        """:meth:`update`'s steps after its draws, with the gradients of the same losses taken
        by :func:`torch.func.grad` and Adam and the guard as tensor ops
        (:mod:`walkers.agents.common.functional`), so that ``torch.compile`` takes them whole:
        ``compile=true`` on the CPU (one graph with the delayed step, one without)."""
        grads, (critic_loss, q_mean) = self.critic_gradient(b, smoothing_noise)
        critic_skipped = guarded_adam_step(
            self.critic_optimizer, grads, critic_loss, self.num_critics
        )
        metrics = {"loss/critic": logged(critic_loss), "train/q_mean": logged(q_mean)}

        actor_skipped = None
        if delayed:
            grads, (actor_loss,) = self.actor_gradient(b)
            actor_skipped = guarded_adam_step(
                self.actor_optimizer, grads, actor_loss, also_skip=critic_skipped
            )
            soft_update(self.critic_target, self.critic, self.tau)
            soft_update(self.actor_target, self.actor, self.tau)
            metrics["loss/actor"] = logged(actor_loss)
        return metrics | self.record_health(critic_skipped, delayed_bad=actor_skipped)

    def functional_gradients(self) -> dict[str, Callable]:
        return {
            "critic_gradient": gradient_of(self.critic, self.critic_loss),
            "actor_gradient": gradient_of(self.actor, lambda b: (self.actor_loss(b),)),
        }

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
            next_q = self.q_values(self.critic_target, b.next_obs, next_action)  # Q'_i, (K, C, N)
            y = b.reward + self.gamma * (1.0 - b.terminated) * next_q.min(dim=1).values
        q = self.q_values(self.critic, b.obs, b.action)  # Q_i(s, a), (K, C, N)
        return self.critics_regression(q, y), q.detach().mean(dim=(1, 2))

    def actor_loss(self, b: Batch) -> torch.Tensor:
        """-Q_1(s, pi(s)) per member ``(K,)``: the deterministic policy gradient on the first
        critic alone (of the batch, TD3 reads only the states)."""
        return -self.q1(b.obs, self.actor(b.obs)).mean(dim=-1)

    # --- checkpoints: the targets are per-member parts too ---------------------------------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        cuts = super().member_cuts(i)
        return cuts | {"actor_target": cuts["actor"], "critic_target": cuts["critic"]}
