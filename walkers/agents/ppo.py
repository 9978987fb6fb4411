"""PPO (Schulman et al. 2017, "Proximal Policy Optimization Algorithms"), continuous control.

The setting of the paper's MuJoCo experiments and of its reference implementations (OpenAI
baselines ``ppo2``, CleanRL ``ppo_continuous_action.py``): a Gaussian policy with a
state-independent log-std and a separate value network, both 64-64 tanh MLPs with orthogonal
initialisation. The agent collects ``n_steps`` env steps with its current policy, then learns
from them (Algorithm 1 of the paper):

    A_t = GAE(gamma, lambda) over the rollout, bootstrapping V(s') where an episode was cut by a
          time limit or by the end of the rollout (a terminal state is never bootstrapped)
    for each of ``n_epochs`` epochs, for each of ``n_minibatches`` shuffled minibatches:
        r_t(theta)  = pi_theta(a_t | s_t) / pi_theta_old(a_t | s_t)
        L^CLIP      = E[ min(r_t A_t, clip(r_t, 1 - eps, 1 + eps) A_t) ]       (A_t normalized
                                                                                 per minibatch)
        L^VF        = E[ 1/2 (V(s_t) - (A_t + V_old(s_t)))^2 ]   (optionally clipped around V_old)
        minimize  -L^CLIP + vf_coef * L^VF - ent_coef * H[pi_theta(. | s_t)]
        with one Adam step, the global gradient norm clipped to ``max_grad_norm``,
    the learning rate annealed linearly to 0 over the run's ``total_steps``.

Observation normalization and reward scaling (:mod:`walkers.agents.common.normalization`) happen
inside the agent, so what the trainer reports (``train/episode_return``, ``eval/*``) are the env's
own returns; their statistics update only while exploring and are saved in the checkpoint.

Action bounds: as in REINFORCE here (and in the reference code), the env receives the Gaussian
sample clipped to its bounds; the log-probability is that of the unclipped sample.

Where this differs from CleanRL (besides the one-env loop): the rollout bootstraps at time-limit
truncations (CleanRL treats them as terminal), values and log-probabilities of the rollout are
computed in one batch at update time (the networks do not change during a rollout, so they equal
the per-step ones), each epoch has exactly ``n_minibatches`` minibatches, ``target_kl`` compares
an epoch's mean approximate KL (CleanRL: its last minibatch's), and a non-finite loss or gradient
skips that minibatch's step (the NaN guard every agent here has). ``health/*`` count those
minibatch steps: one rollout that is all NaN skips ``n_epochs * n_minibatches`` of them in a row,
which with the defaults (320) is more than ``divergence_patience``, and the run ends FAILED (a
NaN reaching the rollout has usually poisoned the normalizer's statistics too).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from walkers.agents.base import Agent, Transition, resolve_device
from walkers.agents.common.health import NonFiniteGuard, clip_or_skip
from walkers.agents.common.normalization import ObservationNormalizer, RewardScaler
from walkers.agents.common.policies import GaussianPolicy, orthogonal_mlp
from walkers.data.rollouts import Rollout, gae
from walkers.seeding import restore_generator, torch_generator

#: Run tag set when a resumed run's checkpoint did not hold the unfinished rollout.
ROLLOUT_RESTART_TAG = "walkers.rollout_restart"


def clipped_surrogate(ratio: torch.Tensor, advantages: torch.Tensor, clip_coef: float):
    """Per-sample loss -min(r A, clip(r, 1 - eps, 1 + eps) A) (the paper's L^CLIP, negated).

    Where clipping binds (r > 1 + eps with A > 0, r < 1 - eps with A < 0) the loss is the clipped
    value and its gradient with respect to r is zero: the update gains nothing from moving r
    further from 1.
    """
    unclipped = ratio * advantages
    clipped = ratio.clamp(1 - clip_coef, 1 + clip_coef) * advantages
    return -torch.minimum(unclipped, clipped)


def value_loss(
    values: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
    clip_coef: float | None,
) -> torch.Tensor:
    """1/2 (V - R)^2 per sample; with ``clip_coef`` the pessimistic max with the loss of V moved
    at most ``clip_coef`` from ``old_values`` (ppo2's and CleanRL's value clipping)."""
    loss = (values - returns).pow(2)
    if clip_coef is not None:
        clipped = old_values + (values - old_values).clamp(-clip_coef, clip_coef)
        loss = torch.maximum(loss, (clipped - returns).pow(2))
    return 0.5 * loss


class PPO(Agent):
    """Hyperparameters: declared, with the MuJoCo reference defaults, in
    walkers.agents.declarations.schemas."""

    several_envs = True  # algo.num_envs: a rollout from several envs acting as one batch

    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        lr: float,
        n_steps: int,
        num_envs: int,
        n_epochs: int,
        n_minibatches: int,
        gamma: float,
        gae_lambda: float,
        clip_coef: float,
        clip_value_loss: bool,
        vf_coef: float,
        ent_coef: float,
        max_grad_norm: float | None,
        target_kl: float | None,
        normalize_advantages: bool,
        hidden_sizes: Sequence[int],
        activation: str,
        log_std_init: float,
        normalize_obs: bool,
        normalize_reward: bool,
        clip_obs: float,
        clip_reward: float,
        anneal_lr: bool,
        total_steps: int | None,
        adam_eps: float,
        device: str = "cpu",
        seed: int = 0,
    ):
        # n_minibatches <= n_steps and num_envs | n_steps: declared (PPOHyperparameters)
        self.device = resolve_device(device)
        self.lr, self.n_steps, self.n_epochs = lr, int(n_steps), int(n_epochs)
        self.num_envs = int(num_envs)  # envs stepped together: a rollout is a stream of each
        self.n_minibatches = int(n_minibatches)
        self.gamma, self.gae_lambda, self.clip_coef = gamma, gae_lambda, clip_coef
        self.value_clip = clip_coef if clip_value_loss else None
        self.vf_coef, self.ent_coef = vf_coef, ent_coef
        self.max_grad_norm, self.target_kl = max_grad_norm, target_kl
        self.normalize_advantages = normalize_advantages
        # linear annealing over the run's updates; without a budget, a constant learning rate
        self.total_updates = total_steps // self.n_steps if anneal_lr and total_steps else None
        self.action_low = np.asarray(action_low, dtype=np.float32)
        self.action_high = np.asarray(action_high, dtype=np.float32)
        act_dim = len(self.action_low)

        torch.manual_seed(seed)
        self.policy = GaussianPolicy(
            orthogonal_mlp(obs_dim, act_dim, hidden_sizes, activation, output_gain=0.01),
            act_dim,
            log_std_init,
        ).to(self.device)
        self.value = orthogonal_mlp(obs_dim, 1, hidden_sizes, activation).to(self.device)
        self.params = [*self.policy.parameters(), *self.value.parameters()]
        self.optimizer = torch.optim.Adam(self.params, lr=lr, eps=adam_eps, fused=True)
        self.obs_normalizer = ObservationNormalizer((obs_dim,), normalize_obs, clip_obs)
        self.reward_scaler = RewardScaler(
            gamma, normalize_reward, clip_reward, num_envs=self.num_envs
        )
        self.rollouts = [Rollout() for _ in range(self.num_envs)]  # one stream per env
        self.steps = 0  # env steps observed
        self.num_updates = 0  # rollouts learned from
        self.guard = NonFiniteGuard(self.device)
        self.generator = torch_generator(seed, "policy", self.device)  # action sampling
        self.minibatch_generator = torch_generator(seed, "replay")  # shuffling (on the CPU)
        self._rollout_dropped = 0

    # --- acting -------------------------------------------------------------------------------
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """For one observation, or a batch ``(num_envs, obs_dim)`` of the envs stepped together."""
        # exploring (training) updates the normalizer's statistics; greedy actions use them frozen
        obs = self.obs_normalizer(obs, update=explore)
        with torch.no_grad():
            dist = self.policy(torch.as_tensor(obs, device=self.device))
            if explore:
                noise = torch.randn(dist.mean.shape, generator=self.generator, device=self.device)
                action = dist.mean + dist.stddev * noise
            else:
                action = dist.mean
        action = action.cpu().numpy()
        if explore:  # what observe() stores: the normalized obs and the unclipped sample
            self._last = (obs, action)
        return np.clip(action, self.action_low, self.action_high)

    def observe(self, t: Transition) -> None:
        if self.num_envs > 1:
            raise ValueError(f"PPO with num_envs={self.num_envs} observes a batch (observe_batch)")
        obs, sample = self._last
        self.rollouts[0].add(
            t.episode_over,
            obs=obs,
            action=sample,
            reward=self.reward_scaler(t.reward, t.episode_over),
            terminated=float(t.terminated),
            # read where the step's own next state is bootstrapped (truncation, rollout end)
            next_obs=self.obs_normalizer(t.next_obs, update=False),
        )
        self.steps += 1

    def observe_batch(self, transitions: Sequence[Transition]) -> None:
        """One step of each of the ``num_envs`` envs, in env order (after a batch ``act``)."""
        obs, sample = self._last
        rewards = self.reward_scaler.scale_batch(
            [t.reward for t in transitions], [t.episode_over for t in transitions]
        )
        next_obs = self.obs_normalizer(np.stack([t.next_obs for t in transitions]), update=False)
        for i, t in enumerate(transitions):
            self.rollouts[i].add(
                t.episode_over,
                obs=obs[i],
                action=sample[i],
                reward=rewards[i],
                terminated=float(t.terminated),
                next_obs=next_obs[i],
            )
        self.steps += len(transitions)

    # --- learning -----------------------------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if len(self.rollouts[0]) < self.n_steps // self.num_envs:
            return {}
        b = self._prepare_batch([rollout.take() for rollout in self.rollouts])
        lr = self._anneal_learning_rate()
        sums = dict.fromkeys(("policy", "value", "entropy", "kl", "clip", "grad"), 0.0)
        minibatches = 0
        for _ in range(self.n_epochs):
            order = torch.randperm(self.n_steps, generator=self.minibatch_generator)
            kl_epoch = 0.0
            for idx in order.to(self.device).tensor_split(self.n_minibatches):
                m = self._minibatch_step(b, idx)
                for key in sums:
                    sums[key] = sums[key] + m[key]
                kl_epoch = kl_epoch + m["kl"]
                minibatches += 1
            # optional early stop when the policy moved too far from the one that collected
            if self.target_kl is not None and kl_epoch.item() / self.n_minibatches > self.target_kl:
                break
        self.num_updates += 1
        metrics = {
            "loss/policy": sums["policy"] / minibatches,
            "loss/value": sums["value"] / minibatches,
            "train/entropy": sums["entropy"] / minibatches,
            "train/approx_kl": sums["kl"] / minibatches,
            "train/clip_fraction": sums["clip"] / minibatches,
            "train/grad_norm": sums["grad"] / minibatches,
            "train/explained_variance": _explained_variance(b["old_values"], b["returns"]),
            "train/lr": torch.tensor(lr),
            "train/log_std_mean": self.policy.log_std.detach().mean(),
        }
        return metrics | self.guard.metrics()

    def _prepare_batch(self, streams: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
        """The rollout (each env's stream, concatenated in env order) as tensors, with the old
        policy's log-probabilities, the old values, the GAE advantages and the value targets."""
        data = {k: np.concatenate([stream[k] for stream in streams]) for k in streams[0]}
        t = {k: torch.as_tensor(v, device=self.device) for k, v in data.items()}
        # each stream ends where its env's part of the rollout ends: its trace stops there and
        # its last step bootstraps, as at an episode's truncation
        stream_end = data["episode_end"].copy()
        stream_end[np.cumsum([len(stream["reward"]) for stream in streams]) - 1] = True
        with torch.no_grad():
            old_log_prob = self.policy(t["obs"]).log_prob(t["action"]).sum(-1)
            values = self.value(t["obs"]).squeeze(-1).cpu().numpy()
            # V(s'_t) is V(s_{t+1}) inside an episode; the value of the step's own next
            # observation where an episode ends (used only after a truncation) and at the end of
            # each env's stream (bootstrapping the unfinished episode)
            next_values = np.append(values[1:], 0.0).astype(np.float32)
            own_next_obs = t["next_obs"][torch.as_tensor(stream_end, device=self.device)]
            next_values[stream_end] = self.value(own_next_obs).squeeze(-1).cpu().numpy()
        advantages, returns = gae(
            data["reward"],
            values,
            next_values,
            data["terminated"] > 0,
            stream_end,
            self.gamma,
            self.gae_lambda,
        )
        return {
            "obs": t["obs"],
            "action": t["action"],
            "old_log_prob": old_log_prob,
            "old_values": torch.as_tensor(values, device=self.device),
            "advantages": torch.as_tensor(advantages, device=self.device),
            "returns": torch.as_tensor(returns, device=self.device),
        }

    def _minibatch_step(self, b: dict[str, torch.Tensor], idx: torch.Tensor) -> dict:
        """One gradient step of the clipped surrogate, value loss and entropy bonus."""
        dist = self.policy(b["obs"][idx])
        log_ratio = dist.log_prob(b["action"][idx]).sum(-1) - b["old_log_prob"][idx]
        ratio = log_ratio.exp()
        advantages = b["advantages"][idx]
        if self.normalize_advantages and len(idx) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        policy_loss = clipped_surrogate(ratio, advantages, self.clip_coef).mean()
        v_loss = value_loss(
            self.value(b["obs"][idx]).squeeze(-1),
            b["old_values"][idx],
            b["returns"][idx],
            self.value_clip,
        ).mean()
        entropy = dist.entropy().sum(-1).mean()
        loss = policy_loss - self.ent_coef * entropy + self.vf_coef * v_loss

        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        skipped, grad_norm = clip_or_skip(self.optimizer, loss, self.max_grad_norm)  # NaN/inf
        self.optimizer.step()
        self.guard.record(skipped)
        with torch.no_grad():  # diagnostics (k3 estimator of KL(old || new), Schulman 2020)
            approx_kl = ((ratio - 1) - log_ratio).mean()
            clip_fraction = ((ratio - 1).abs() > self.clip_coef).float().mean()
        return {
            "policy": policy_loss.detach(),
            "value": v_loss.detach(),
            "entropy": entropy.detach(),
            "kl": approx_kl,
            "clip": clip_fraction,
            "grad": grad_norm,
        }

    def _anneal_learning_rate(self) -> float:
        """lr * (1 - updates so far / updates in the run); constant without annealing."""
        lr = self.lr
        if self.total_updates:
            lr = self.lr * max(0.0, 1.0 - self.num_updates / self.total_updates)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        return lr

    # --- checkpoints --------------------------------------------------------------------------
    def state_dict(self, with_buffer: bool = False) -> dict:
        """Networks, optimizer, normalizer statistics, counters, RNGs; with ``with_buffer`` also
        the unfinished rollout (the local resume copy always has it)."""
        state = {
            "policy": self.policy.state_dict(),
            "value": self.value.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "obs_normalizer": self.obs_normalizer.state_dict(),
            "reward_scaler": self.reward_scaler.state_dict(),
            "steps": self.steps,
            "num_updates": self.num_updates,
            "rollout_steps": sum(len(rollout) for rollout in self.rollouts),
            "guard": self.guard.state_dict(),
            "generator": self.generator.get_state(),
            "minibatch_generator": self.minibatch_generator.get_state(),
        }
        if with_buffer:  # one env: "rollout", as before there were several
            streams = [rollout.state_dict() for rollout in self.rollouts]
            state |= {"rollout": streams[0]} if self.num_envs == 1 else {"rollouts": streams}
        return state

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state["policy"])
        self.value.load_state_dict(state["value"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.obs_normalizer.load_state_dict(state["obs_normalizer"])
        self.reward_scaler.load_state_dict(state["reward_scaler"])
        self.steps, self.num_updates = state["steps"], state["num_updates"]
        self.guard.load_state_dict(state["guard"])
        restore_generator(self.generator, state["generator"], "PPO's action sampler")
        restore_generator(
            self.minibatch_generator, state["minibatch_generator"], "PPO's minibatch shuffler"
        )
        # A resumed run starts a new episode (the interrupted one cannot be continued): the
        # rollout's last episode is cut there, a truncation that bootstraps from V(s').
        saved = state.get("rollouts", [state["rollout"]] if "rollout" in state else None)
        self.rollouts = [Rollout() for _ in range(self.num_envs)]
        for rollout, stream in zip(self.rollouts, saved or [], strict=False):
            rollout.load_state_dict(stream)
            rollout.cut()
        self.reward_scaler.new_episode()
        self._rollout_dropped = state["rollout_steps"] if saved is None else 0

    def resume_notes(self) -> dict[str, str]:
        if not self._rollout_dropped:
            return {}
        return {
            ROLLOUT_RESTART_TAG: f"{self._rollout_dropped} steps of the unfinished rollout were "
            f"not in the checkpoint: a new rollout of {self.n_steps} steps starts at step "
            f"{self.steps}"
        }


def _explained_variance(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1 - Var[target - predicted] / Var[target]: 1 is a perfect value function, 0 no better than
    a constant (NaN when the targets do not vary)."""
    var = target.var()
    return torch.where(var > 0, 1 - (target - predicted).var() / var, torch.nan)
