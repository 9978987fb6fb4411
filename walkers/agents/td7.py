"""TD7 (Fujimoto, Chang, Smith, Gu, Precup, Meger, NeurIPS 2023, "For SALE: State-Action
Representation Learning for Deep Reinforcement Learning"), Algorithm 1, as the authors' code
(github.com/sfujim/TD7, ``TD7.py``) runs it online without policy checkpoints.

TD3 (:mod:`walkers.agents.td3`: twin critics with the min, target policy smoothing, a delayed
actor) with four additions:

- **SALE**: an encoder learns embeddings zs = f(s) and zsa = g(zs, a) by predicting the next
  state's embedding, ``min ||g(f(s), a) - sg(f(s'))||^2``. The actor reads pi(s, zs), the critics
  Q(s, a, zsa, zs); both read the embeddings of a *fixed* copy of the encoder (f_t, g_t), and
  their targets those of the copy before it (f_t-1, g_t-1). AvgL1Norm (x / mean |x|) keeps the
  embeddings' scale and the first layers' outputs in step.
- **LAP**: the replay buffer samples a transition with probability proportional to
  max(|delta|, 1)^alpha, its last TD error's; the critics' loss is the Huber loss that makes that
  sampling unbiased (quadratic below 1, linear above).
- **Hard target updates** every ``target_update_rate`` (250) updates: the target actor and
  critics, both fixed encoders, LAP's largest priority and the value clipping's bounds.
- **Value clipping**: the target's Q' is clamped into the range of the targets seen before the
  last target update (extrapolation error cannot run away).

:meth:`TD7.learn`, every update (one graph per way through it when captured):

    sample N transitions by LAP priority                                          (sample)
    encoder step on N^-1 sum ||g(f(s), a) - sg(f(s'))||^2                          (encoder_loss)
    a~ <- clip(pi'(s', zs'') + clip(eps, -c, c), -1, 1), zs'' = f_t-1(s')          (critic_loss)
    y <- r + gamma (1 - d) clip(min_i Q'_i(s', a~, g_t-1(zs'', a~), zs''), lo, hi)  (critic_loss)
    critics' step on N^-1 sum_i LAP-Huber(|y - Q_i(s, a, g_t(zs, a), zs)|), zs = f_t(s)
    priorities of the batch <- max(max_i |y - Q_i|, 1)^alpha
    if t mod d = 0: actor step on -N^-1 sum mean_i Q_i(s, pi(s, zs), g_t(zs, pi), zs)

and :meth:`TD7.update` adds, every ``target_update_rate``-th update, :meth:`update_targets`.

Where this differs from the paper: no policy checkpoints (the paper's fourth idea, which acts
with the best checkpointed policy and trains between episodes; the authors' code runs without
them with ``--no-use_checkpoints``, and the paper's ablation scores that variant). Actions are
scaled to [-1, 1] inside the update, as the authors' buffer stores them.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from walkers.agents.common.actor_critic import ActorCritic, frozen, logged
from walkers.agents.common.health import skip_nonfinite
from walkers.agents.common.networks import EnsembleLinear
from walkers.agents.td3 import TD3
from walkers.data.replay import Batch, ReplayBuffer


def avg_l1_norm(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """AvgL1Norm(x) = x / max(mean |x|, eps) over the last dimension."""
    return x / x.abs().mean(dim=-1, keepdim=True).clamp(min=eps)


def lap_huber(td: torch.Tensor, min_priority: float) -> torch.Tensor:
    """LAP's critic loss per member ``(K,)`` for absolute TD errors ``(K, C, N)``: 1/2 delta^2
    below ``min_priority``, ``min_priority`` delta above, summed over the critics, mean over N."""
    loss = torch.where(td < min_priority, 0.5 * td.pow(2), min_priority * td)
    return loss.sum(dim=1).mean(dim=-1)


def ensemble_layers(n: int, dims: Sequence[int]) -> nn.ModuleList:
    return nn.ModuleList(EnsembleLinear(n, a, b) for a, b in zip(dims[:-1], dims[1:], strict=True))


class SALEEncoder(nn.Module):
    """f(s) -> zs and g(zs, a) -> zsa of ``n`` members (ELU hidden layers; zs AvgL1-normed)."""

    def __init__(self, n, obs_dim, act_dim, zs_dim: int, hidden_sizes: Sequence[int]):
        super().__init__()
        self.state_layers = ensemble_layers(n, [obs_dim, *hidden_sizes, zs_dim])
        self.state_action_layers = ensemble_layers(n, [zs_dim + act_dim, *hidden_sizes, zs_dim])

    @staticmethod
    def _run(layers: nn.ModuleList, x: torch.Tensor, members: slice) -> torch.Tensor:
        for layer in layers[:-1]:
            x = F.elu(layer(x, members))
        return layers[-1](x, members)

    def zs(self, obs: torch.Tensor, members: slice = slice(None)) -> torch.Tensor:
        return avg_l1_norm(self._run(self.state_layers, obs, members))

    def zsa(self, zs: torch.Tensor, action: torch.Tensor, members=slice(None)) -> torch.Tensor:
        return self._run(self.state_action_layers, torch.cat([zs, action], dim=-1), members)


class SALEActor(nn.Module):
    """pi(s, zs) of ``n`` members: AvgL1Norm(W0 s) (``hidden_sizes[0]`` wide) beside zs, then
    ReLU layers of ``hidden_sizes`` and tanh, in [-1, 1] (the authors' l0, l1, l2, l3).

    It holds the fixed encoder it acts through (:attr:`encoder`, set by :class:`TD7`: a frozen
    copy, moved by :meth:`TD7.update_targets` and not by the actor's optimizer), so
    ``actor(obs)`` is the acting policy in the env's action bounds, as every actor's is."""

    encoder: SALEEncoder

    def __init__(self, n, obs_dim, act_dim, hidden_sizes, action_low, action_high, zs_dim: int):
        super().__init__()
        self.state_layer = EnsembleLinear(n, obs_dim, hidden_sizes[0])
        self.layers = ensemble_layers(n, [hidden_sizes[0] + zs_dim, *hidden_sizes, act_dim])
        low = torch.as_tensor(action_low, dtype=torch.float32)
        high = torch.as_tensor(action_high, dtype=torch.float32)
        self.register_buffer("action_scale", (high - low) / 2, persistent=False)
        self.register_buffer("action_bias", (high + low) / 2, persistent=False)

    def pi(self, obs: torch.Tensor, zs: torch.Tensor, members=slice(None)) -> torch.Tensor:
        """The action in [-1, 1] for states and their embeddings."""
        x = torch.cat([avg_l1_norm(self.state_layer(obs, members)), zs], dim=-1)
        for layer in self.layers[:-1]:
            x = F.relu(layer(x, members))
        return torch.tanh(self.layers[-1](x, members))

    def forward(self, obs: torch.Tensor, members: slice = slice(None)) -> torch.Tensor:
        action = self.pi(obs, self.encoder.zs(obs, members), members)
        return action * self.action_scale + self.action_bias


class SALECritic(nn.Module):
    """Q(s, a, zsa, zs) of ``n`` critics: AvgL1Norm(W0 [s, a]) (``hidden_sizes[0]`` wide)
    beside [zsa, zs], then ELU layers of ``hidden_sizes`` (the authors' q01, q1, q2, q3)."""

    def __init__(self, obs_dim, act_dim, hidden_sizes: Sequence[int], n: int, zs_dim: int):
        super().__init__()
        self.state_action_layer = EnsembleLinear(n, obs_dim + act_dim, hidden_sizes[0])
        self.layers = ensemble_layers(n, [hidden_sizes[0] + 2 * zs_dim, *hidden_sizes, 1])

    def forward(self, obs, action, zsa, zs) -> torch.Tensor:
        sa = avg_l1_norm(self.state_action_layer(torch.cat([obs, action], dim=-1)))
        x = torch.cat([sa, zsa, zs], dim=-1)
        for layer in self.layers[:-1]:
            x = F.elu(layer(x))
        return self.layers[-1](x).squeeze(-1)


class ValueClip(nn.Module):
    """Per member: the bounds the target's Q' is clipped to (``low``, ``high``: the authors'
    start at 0, 0) and the range of the targets seen since (``seen_low``, ``seen_high``)."""

    def __init__(self, n: int):
        super().__init__()
        for name, value in (("low", 0.0), ("high", 0.0), ("seen_low", 1e8), ("seen_high", -1e8)):
            self.register_buffer(name, torch.full((n,), value))

    @torch.no_grad()
    def see(self, y: torch.Tensor) -> None:
        """Widen the seen range by the targets ``y`` ``(K, N)`` (in place: graphs replay it).
        A NaN target widens nothing (``fmin``/``fmax``), as in the authors' Python ``min``/``max``:
        a member whose batch held one (its update skipped by the guard) keeps its bounds."""
        self.seen_low.copy_(torch.fmin(self.seen_low, y.min(dim=1).values))
        self.seen_high.copy_(torch.fmax(self.seen_high, y.max(dim=1).values))

    @torch.no_grad()
    def advance(self) -> None:
        """At a target update: clip to the range seen so far."""
        self.low.copy_(self.seen_low)
        self.high.copy_(self.seen_high)


class PrioritizedReplay(ReplayBuffer):
    """LAP's buffer: each member's transitions with a priority (new ones get the member's
    largest so far), sampled in proportion to it in one op for all members (a cumulative sum
    and a search per member: on a GPU over the whole capacity, so a captured graph samples a
    growing buffer, unfilled rows having priority 0; on a CPU over the filled rows)."""

    def __init__(self, capacity, obs_dim, act_dim, device="cpu", seeds=(0,)):
        super().__init__(capacity, obs_dim, act_dim, device, seeds)
        self.priority = torch.zeros(self.members, self.capacity, device=self.device)
        self.max_priority = torch.ones(self.members, device=self.device)

    def add(self, obs, action, reward, next_obs, terminated, episode_end=False) -> None:
        self.priority[:, self.pos] = self.max_priority
        super().add(obs, action, reward, next_obs, terminated, episode_end)

    def draw_rows(self, batch_size: int) -> torch.Tensor:
        """``(K, batch_size)`` rows, each member's in proportion to its priorities. On a CPU
        (never captured) only the filled rows are summed: the same rows, drawn in a tenth of
        the time at 100k of 1M."""
        filled = self.size if self.device.type == "cpu" else self.capacity
        cumulative = self.priority[:, :filled].cumsum(dim=1)
        uniform = self.sampler.uniform(batch_size)
        return torch.searchsorted(cumulative, uniform * cumulative[:, -1:])

    @torch.no_grad()
    def update_priority(self, idx: torch.Tensor, priority: torch.Tensor, keep: torch.Tensor):
        """The sampled rows' new priorities ``(K, N)``; members where ``keep`` is 1 (their
        critics' step was skipped) keep theirs."""
        rows = self._rows
        priority = torch.where(keep.unsqueeze(1) > 0, self.priority[rows, idx], priority)
        self.priority[rows, idx] = priority
        self.max_priority.copy_(torch.maximum(self.max_priority, priority.max(dim=1).values))

    @torch.no_grad()
    def reset_max_priority(self) -> None:
        self.max_priority.copy_(self.priority.max(dim=1).values)

    def member_state_dict(self, i: int, with_data: bool) -> dict:
        state = super().member_state_dict(i, with_data)
        state["max_priority"] = float(self.max_priority[i])
        if with_data:
            state["data"]["priority"] = self.priority[i, : self.size].cpu().clone()
        return state

    def load_member_state_dict(self, i: int, state: dict) -> None:
        super().load_member_state_dict(i, state)  # loads the priorities with the data
        if "data" not in state:  # refilled from empty
            self.priority[i].zero_()
        self.max_priority[i] = state.get("max_priority", 1.0)


class TD7(ActorCritic):
    """TD7 without policy checkpoints (see the module docstring); hyperparameters (the authors',
    declared in :mod:`walkers.agents.declarations.schemas`) are the core's, TD3's smoothing and
    delay, and SALE's and LAP's."""

    num_critics = 2
    compiled_losses = ("encoder_loss", "critic_loss", "actor_loss")
    captured_step = "learn"  # the hard target copies every 250 updates stay outside the graphs
    replay_class = PrioritizedReplay

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        exploration_noise: float,
        policy_noise: float,
        noise_clip: float,
        policy_delay: int,
        target_update_rate: int,
        lap_alpha: float,
        min_priority: float,
        zs_dim: int,
        encoder_hidden_sizes: Sequence[int],
        lr: float,
        **core,
    ):
        super().__init__(obs_dim, action_low, action_high, lr=lr, **core)
        self.exploration_sigma, self.noise_type = exploration_noise, "gaussian"
        self.policy_noise, self.noise_clip = policy_noise, noise_clip
        self.policy_delay, self.target_update_rate = policy_delay, target_update_rate
        self.lap_alpha, self.min_priority = lap_alpha, min_priority
        self.noise_scale = (self.action_high - self.action_low) / 2

        self.actor = self.build_actor(SALEActor, zs_dim=zs_dim)  # pi
        self.critic = self.build_critic(SALECritic, zs_dim=zs_dim)  # Q_1, Q_2
        self.encoder = self._per_member(  # f, g: learned
            lambda n: SALEEncoder(n, obs_dim, self.act_dim, zs_dim, encoder_hidden_sizes).to(
                self.device
            ),
            1,
        )
        self.actor.encoder = self.target_of(self.encoder)  # f_t, g_t: what acting reads
        self.actor_target = self.target_of(self.actor)  # pi', with f_t-1, g_t-1
        self.critic_target = self.target_of(self.critic)
        self.value_clip = ValueClip(self.population).to(self.device)
        self.encoder_optimizer = self.adam(self.encoder, lr)
        self.critic_optimizer = self.adam(self.critic, self.critic_lr)
        self.actor_optimizer = self.adam(self.actor, self.actor_lr)  # its encoder is frozen
        self.members = self.build_members(self.exploration_noise)
        self.compile_update()

    @property
    def update_period(self) -> int:
        return self.policy_delay

    # --- acting: a ~ clip(pi(s, f_t(s)) + eps, low, high), TD3's with the actor reading f_t ------
    exploration_noise = TD3.exploration_noise
    policy = TD3.policy

    # --- learning: Algorithm 1 ---------------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        metrics = self.learn()
        if metrics and self.num_updates % self.target_update_rate == 0:
            self.update_targets()
        return metrics

    def learn(self) -> dict[str, torch.Tensor]:
        if not self.begin_update():
            return {}
        b = self.sample()
        action = self.unit_action(b.action)  # a in [-1, 1], as the critics and encoders read it
        smoothing_noise = self.noise_like(action)

        encoder_loss = self.encoder_loss(b.obs, action, b.next_obs)
        self.encoder_optimizer.zero_grad(set_to_none=True)
        encoder_loss.sum().backward()
        encoder_skipped = skip_nonfinite(self.encoder_optimizer, encoder_loss)
        self.encoder_optimizer.step()

        critic_loss, td, zs, q_mean = self.critic_loss(b, action, smoothing_noise)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.sum().backward()
        critic_skipped = skip_nonfinite(self.critic_optimizer, critic_loss, self.num_critics)
        self.critic_optimizer.step()
        priority = td.max(dim=1).values.clamp(min=self.min_priority).pow(self.lap_alpha)
        self.buffer.update_priority(b.index, priority, keep=critic_skipped)
        metrics = {
            "loss/encoder": logged(encoder_loss),
            "loss/critic": logged(critic_loss),
            "train/q_mean": logged(q_mean),
        }

        actor_skipped = None
        if self.num_updates % self.policy_delay == 0:
            with frozen(self.critic):
                actor_loss = self.actor_loss(b.obs, zs)
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.sum().backward()
            actor_skipped = skip_nonfinite(
                self.actor_optimizer, actor_loss, also_skip=critic_skipped
            )
            self.actor_optimizer.step()
            metrics["loss/actor"] = logged(actor_loss)
        bad = torch.maximum(encoder_skipped, critic_skipped)
        return metrics | self.record_health(bad, delayed_bad=actor_skipped)

    @torch.no_grad()
    def update_targets(self) -> None:
        """Every ``target_update_rate`` updates, all in place (graphs read the same tensors):
        pi' <- pi and f_t-1 <- f_t (the actor holds f_t), Q' <- Q, f_t <- f, LAP's largest
        priority recomputed, the value clipping's bounds <- the range seen."""
        for target, source in (
            (self.actor_target, self.actor),
            (self.critic_target, self.critic),
            (self.actor.encoder, self.encoder),
        ):
            for t, s in zip(target.parameters(), source.parameters(), strict=True):
                t.copy_(s)
        self.buffer.reset_max_priority()
        self.value_clip.advance()

    def unit_action(self, action: torch.Tensor) -> torch.Tensor:
        return (action - self.actor.action_bias) / self.actor.action_scale

    def encoder_loss(self, obs, action, next_obs) -> torch.Tensor:
        """N^-1 sum mean (g(f(s), a) - sg(f(s')))^2 per member ``(K,)``."""
        with torch.no_grad():
            next_zs = self.encoder.zs(next_obs)
        predicted = self.encoder.zsa(self.encoder.zs(obs), action)
        return (predicted - next_zs).pow(2).mean(dim=(1, 2))

    def critic_loss(self, b: Batch, action: torch.Tensor, smoothing_noise: torch.Tensor):
        """Per member ``(K,)``: the LAP-Huber loss of both critics against the clipped target;
        with the absolute TD errors ``(K, C, N)``, f_t(s) (for the actor) and mean Q ``(K,)``."""
        target_encoder, fixed_encoder = self.actor_target.encoder, self.actor.encoder
        with torch.no_grad():
            next_zs = target_encoder.zs(b.next_obs)
            eps = (smoothing_noise * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)
            next_action = (self.actor_target.pi(b.next_obs, next_zs) + eps).clamp(-1.0, 1.0)
            next_zsa = target_encoder.zsa(next_zs, next_action)
            next_q = self.q(self.critic_target, b.next_obs, next_action, next_zsa, next_zs)
            clip = self.value_clip
            next_v = next_q.min(dim=1).values.clamp(clip.low[:, None], clip.high[:, None])
            y = b.reward + self.gamma * (1.0 - b.terminated) * next_v
            clip.see(y)
            zs = fixed_encoder.zs(b.obs)
            zsa = fixed_encoder.zsa(zs, action)
        q = self.q(self.critic, b.obs, action, zsa, zs)
        td = (q - y.unsqueeze(1)).abs()
        return lap_huber(td, self.min_priority), td.detach(), zs, q.detach().mean(dim=(1, 2))

    def actor_loss(self, obs: torch.Tensor, zs: torch.Tensor) -> torch.Tensor:
        """-mean_i Q_i(s, pi(s, zs), g_t(zs, pi), zs) per member ``(K,)`` (both critics)."""
        action = self.actor.pi(obs, zs)
        zsa = self.actor.encoder.zsa(zs, action)
        return -self.q(self.critic, obs, action, zsa, zs).mean(dim=(1, 2))

    def q(self, critic, obs, action, zsa, zs) -> torch.Tensor:
        """Q_i of every member's critics ``(K, C, N)`` for ``(K, N, d)`` inputs."""
        per_critic = map(self._per_critic, (obs, action, zsa, zs))
        return critic(*per_critic).unflatten(0, (self.population, self.num_critics))

    # --- checkpoints ---------------------------------------------------------------------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        cuts = super().member_cuts(i)
        own = cuts["actor"]
        return cuts | {
            "actor_target": own,
            "critic_target": cuts["critic"],
            "encoder": own,
            "encoder_optimizer": own,
            "value_clip": own,
        }
