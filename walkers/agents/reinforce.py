"""REINFORCE (Williams 1992) for continuous actions, with the original study's stabilizers.

The policy is a Gaussian with a state-dependent mean and a learned, state-independent log-std.
After every ``episodes_per_update`` complete episodes it takes one gradient step on

    L(theta) = - sum_t log pi(a_t | s_t) * G_t  (/ number of steps)   [- entropy_coef * H]

with G_t the discounted return-to-go. Stabilizers (each a switch, on by default):

- ``normalize_returns``: G_t standardized over the batch, keeping gradient magnitudes bounded;
- ``max_grad_norm``: global gradient-norm clipping against destructive updates;
- ``log_std_min`` / ``log_std_max``: log-std clamped so the policy neither collapses (std -> 0)
  nor becomes uniform noise (std -> inf);
- a non-finite guard: a step whose loss or gradients are NaN/inf is skipped (the policy's and
  the baseline's each on its own), and the update counted (``health/skipped_updates``) on the
  device, instead of poisoning the weights.

``baseline=true`` adds a learned state-value baseline V(s) (advantage G_t - V(s_t)); off by
default so the default is the plain no-baseline REINFORCE of the study.

Action bounds: the Gaussian sample is *clipped* to the env's bounds when executed, and the
log-probability in the gradient is that of the unclipped sample (the usual choice, e.g. in
Stable-Baselines3 and Tianshou). Squashing with tanh would change the density; clipping keeps
the estimator unbiased for the Gaussian policy that was actually sampled.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from walkers.agents.base import Agent, Transition, resolve_device
from walkers.agents.common.health import NonFiniteGuard, clip_or_skip
from walkers.agents.common.networks import mlp
from walkers.agents.common.policies import GaussianPolicy
from walkers.data.rollouts import Rollout, returns_to_go
from walkers.seeding import restore_generator, torch_generator


class Reinforce(Agent):
    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        lr: float,
        hidden_sizes: Sequence[int],
        gamma: float,
        episodes_per_update: int,
        normalize_returns: bool,
        max_grad_norm: float | None,
        log_std_init: float,
        log_std_min: float | None,
        log_std_max: float | None,
        baseline: bool,
        baseline_lr: float,
        entropy_coef: float,
        device: str = "cpu",
        seed: int = 0,
    ):
        self.device = resolve_device(device)
        self.gamma, self.episodes_per_update = gamma, int(episodes_per_update)
        self.normalize_returns, self.max_grad_norm = normalize_returns, max_grad_norm
        self.entropy_coef = entropy_coef
        self.action_low = np.asarray(action_low, dtype=np.float32)
        self.action_high = np.asarray(action_high, dtype=np.float32)
        torch.manual_seed(seed)
        act_dim = len(self.action_low)
        self.policy = GaussianPolicy(
            mlp(obs_dim, act_dim, hidden_sizes), act_dim, log_std_init, log_std_min, log_std_max
        ).to(self.device)
        self.optimizer = torch.optim.Adam(self.policy.parameters(), lr=lr, fused=True)
        self.value = self.value_optimizer = None
        if baseline:
            self.value = mlp(obs_dim, 1, hidden_sizes).to(self.device)
            self.value_optimizer = torch.optim.Adam(
                self.value.parameters(), lr=baseline_lr, fused=True
            )
        self.episodes = Rollout()  # whole episodes are learned from, an unfinished one waits
        self.steps = 0
        self.guard = NonFiniteGuard(self.device)
        self.generator = torch_generator(seed, "policy", self.device)

    # --- acting -------------------------------------------------------------------------------
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        with torch.no_grad():
            dist = self.policy(torch.as_tensor(obs, dtype=torch.float32, device=self.device))
            if explore:
                noise = torch.randn(dist.mean.shape, generator=self.generator, device=self.device)
                action = dist.mean + dist.stddev * noise
            else:
                action = dist.mean
        # The unclipped sample is what the gradient needs; observe() receives the executed
        # (clipped) action, so keep the sample.
        self._last_sample = action.cpu().numpy()
        return np.clip(self._last_sample, self.action_low, self.action_high)

    def observe(self, t: Transition) -> None:
        self.episodes.add(t.episode_over, obs=t.obs, actions=self._last_sample, rewards=t.reward)
        self.steps += 1

    # --- learning -----------------------------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if self.episodes.num_episodes < self.episodes_per_update:
            return {}
        # Note: a time-limit truncation ends the Monte-Carlo return there (no bootstrap): the
        # plain REINFORCE estimator has no value function to bootstrap from.
        episodes = self.episodes.pop_episodes()
        obs = torch.as_tensor(np.concatenate([e["obs"] for e in episodes]), device=self.device)
        actions = torch.as_tensor(
            np.concatenate([e["actions"] for e in episodes]), device=self.device
        )
        returns = torch.as_tensor(
            np.concatenate([returns_to_go(e["rewards"], self.gamma) for e in episodes]),
            device=self.device,
        )
        metrics = {}
        advantages = returns
        if self.value is not None:
            values = self.value(obs).squeeze(-1)
            value_loss = (values - returns).pow(2).mean()
            advantages = returns - values.detach()
            metrics["loss/value"] = value_loss.detach()
        if self.normalize_returns and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

        dist = self.policy(obs)
        log_prob = dist.log_prob(actions).sum(-1)
        entropy = dist.entropy().sum(-1).mean()
        loss = -(log_prob * advantages).mean() - self.entropy_coef * entropy
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        skipped, grad_norm = clip_or_skip(self.optimizer, loss, self.max_grad_norm)  # NaN/inf
        self.optimizer.step()
        if self.value is not None:  # the baseline's step, skipped on its own NaN/inf
            self.value_optimizer.zero_grad(set_to_none=True)
            value_loss.backward()
            baseline_skipped, _ = clip_or_skip(self.value_optimizer, value_loss, max_grad_norm=None)
            self.value_optimizer.step()
            skipped = torch.maximum(skipped, baseline_skipped)
        self.guard.record(skipped)  # counted once: this update skipped a step
        metrics.update(
            {
                "loss/policy": loss.detach(),
                "train/entropy": entropy.detach(),
                "train/grad_norm": grad_norm,
                "train/log_std_mean": self.policy.log_std.detach().mean(),
            }
            | self.guard.metrics()
        )
        return metrics

    # --- checkpoints --------------------------------------------------------------------------
    def state_dict(self, with_buffer: bool = False) -> dict:
        state = {
            "policy": self.policy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "steps": self.steps,
            "guard": self.guard.state_dict(),
            "generator": self.generator.get_state(),
        }
        if self.value is not None:
            state["value"] = self.value.state_dict()
            state["value_optimizer"] = self.value_optimizer.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.steps = state["steps"]
        self.guard.load_state_dict(state["guard"])
        restore_generator(self.generator, state["generator"], "REINFORCE's action sampler")
        if self.value is not None:
            self.value.load_state_dict(state["value"])
            self.value_optimizer.load_state_dict(state["value_optimizer"])
