"""Decision Transformer (Chen et al. 2021, "Decision Transformer: Reinforcement Learning via
Sequence Modeling"): offline RL as return-conditioned behaviour cloning.

Training (:meth:`DecisionTransformer.update`, the reference ``SequenceTrainer.train_step``): sample
windows of K steps from the dataset, predict every action from the returns-to-go, states and
earlier actions before it, minimise the mean squared error to the dataset's actions. AdamW with
linear learning-rate warm-up, gradient-norm clipping at 0.25.

Acting (:meth:`act`, the reference ``evaluate_episode_rtg``): start an episode with a target
return ``R``; feed the last K (return-to-go, state, action) steps, take the predicted action, and
after each reward ``r`` the next return-to-go is ``R - r``. A higher target asks for a better
episode: that is the conditioning a return-conditioned policy learns from mixed-quality data.

States are normalized with the dataset's mean and std, actions mapped to [-1, 1], returns divided
by ``return_scale`` (1000 for the MuJoCo walkers in the reference code; per env in conf/env/).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from walkers.agents.base import Agent, autocast, resolve_device, warn_if_slow_precision
from walkers.agents.common.health import NonFiniteGuard, clip_or_skip
from walkers.agents.common.transformer import DecisionTransformerModel
from walkers.data.sequences import SequenceSampler
from walkers.seeding import stream_seeds


class DecisionTransformer(Agent):
    """Hyperparameters: declared, with the reference defaults, in
    walkers.agents.declarations.schemas."""

    offline = True
    return_conditioned = True  # acts toward target_return; evaluated per target_returns

    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        dataset=None,  # walkers.data.datasets.OfflineData; None when only restoring a policy to act
        context_length: int,
        embed_dim: int,
        n_layers: int,
        n_heads: int,
        dropout: float,
        lr: float,
        weight_decay: float,
        warmup_steps: int,
        batch_size: int,
        grad_clip: float,
        precision: str,
        max_episode_steps: int,
        return_scale: float,
        target_returns: Sequence[float] | None,
        device: str = "cpu",
        seed: int = 0,
    ):
        if embed_dim % n_heads:
            raise ValueError(f"embed_dim={embed_dim} must be a multiple of n_heads={n_heads}")
        self.device = resolve_device(device)
        self.context, self.batch_size, self.grad_clip = context_length, batch_size, grad_clip
        self.precision = precision
        warn_if_slow_precision(self.device, precision)
        self.return_scale, self.max_timestep = float(return_scale), int(max_episode_steps)
        low = np.asarray(action_low, dtype=np.float32)
        high = np.asarray(action_high, dtype=np.float32)
        self.action_center, self.action_half_range = (high + low) / 2, (high - low) / 2
        self.action_low, self.action_high = low, high
        act_dim = len(low)

        torch.manual_seed(seed)
        self.model = DecisionTransformerModel(
            obs_dim, act_dim, self.max_timestep, embed_dim, n_layers, n_heads, dropout
        ).to(self.device)
        self.optimizer = torch.optim.AdamW(
            self.model.parameters(), lr=lr, weight_decay=weight_decay, fused=True
        )
        warmup = max(1, int(warmup_steps))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda step: min((step + 1) / warmup, 1.0)
        )
        self.guard = NonFiniteGuard(self.device)
        self.num_updates = 0

        self.obs_mean = np.zeros(obs_dim, dtype=np.float32)
        self.obs_std = np.ones(obs_dim, dtype=np.float32)
        self.target_returns = [float(r) for r in target_returns] if target_returns else []
        self.sampler = None
        if dataset is not None:
            self._attach(dataset, seed)
        self.target_return = self.target_returns[0] if self.target_returns else 0.0
        self._context: dict[str, list[torch.Tensor]] | None = None
        self._step = 0

    def _attach(self, dataset, seed: int) -> None:
        observations = np.concatenate([e.observations[:-1] for e in dataset.episodes])
        self.obs_mean = observations.mean(axis=0).astype(np.float32)
        self.obs_std = (observations.std(axis=0) + 1e-6).astype(np.float32)
        if not self.target_returns:  # default: ask for the best episode in the data
            self.target_returns = [float(dataset.returns.max())]
        self.sampler = SequenceSampler(
            dataset.episodes,
            self.context,
            obs_mean=self.obs_mean,
            obs_std=self.obs_std,
            action_center=self.action_center,
            action_half_range=self.action_half_range,
            return_scale=self.return_scale,
            max_timestep=self.max_timestep,
            device=self.device,
            seed=stream_seeds(seed, "replay")[0],
        )

    # --- acting: one episode, conditioned on self.target_return --------------------------------
    def begin_episode(self) -> None:
        target = torch.tensor(self.target_return / self.return_scale, device=self.device)
        self._context = {"returns_to_go": [target], "obs": [], "actions": []}
        self._step = 0  # the episode timestep of the next observation

    def act(self, obs: np.ndarray, explore: bool = False) -> np.ndarray:
        """The predicted action (a DT does not explore: ``explore`` is ignored)."""
        if self._context is None:
            self.begin_episode()
        c = self._context
        normalized = (np.asarray(obs, dtype=np.float32) - self.obs_mean) / self.obs_std
        c["obs"].append(torch.as_tensor(normalized, device=self.device))
        c["actions"].append(torch.zeros(len(self.action_low), device=self.device))
        for window in c.values():  # the last K steps are all the model reads
            del window[: -self.context]
        n = len(c["obs"])
        timesteps = torch.arange(self._step - n + 1, self._step + 1, device=self.device)
        self.model.eval()
        with torch.no_grad(), autocast(self.device, self.precision):
            predicted = self.model(
                torch.stack(c["returns_to_go"])[None],
                torch.stack(c["obs"])[None],
                torch.stack(c["actions"])[None],
                timesteps.clamp(max=self.max_timestep - 1)[None],
            )[0, -1].float()
        c["actions"][-1] = predicted
        action = predicted.cpu().numpy() * self.action_half_range + self.action_center
        return np.clip(action, self.action_low, self.action_high).astype(np.float32)

    def record_reward(self, reward: float) -> None:
        rtg = self._context["returns_to_go"]
        rtg.append(rtg[-1] - reward / self.return_scale)
        self._step += 1

    # --- learning ---------------------------------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        if self.sampler is None:
            raise RuntimeError("a Decision Transformer needs a dataset to learn from")
        self.model.train()
        b = self.sampler.sample(self.batch_size)
        with autocast(self.device, self.precision):
            predicted = self.model(b.returns_to_go, b.obs, b.actions, b.timesteps)
        squared_error = (predicted.float() - b.actions).pow(2).mean(dim=-1)
        loss = (squared_error * b.mask).sum() / b.mask.sum()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        skipped, grad_norm = clip_or_skip(self.optimizer, loss, self.grad_clip)  # NaN/inf
        self.optimizer.step()
        # the schedule counts updates, skipped or not (stepping it only after a taken step would
        # need the verdict on the host, a sync)
        self.scheduler.step()
        self.guard.record(skipped)  # NaN/inf: the step was skipped (the warm-up goes on)
        self.num_updates += 1
        return {
            "loss/action": loss.detach(),
            "train/grad_norm": grad_norm,
        } | self.guard.metrics()

    # --- checkpoints ------------------------------------------------------------------------
    def state_dict(self, with_buffer: bool = False) -> dict:
        """The dataset itself is not saved: a resumed run reloads it by name."""
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "sampler": self.sampler.state_dict() if self.sampler is not None else None,
            "guard": self.guard.state_dict(),
            "num_updates": self.num_updates,
            "obs_mean": self.obs_mean,
            "obs_std": self.obs_std,
            "target_returns": self.target_returns,
        }

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if self.sampler is not None and state["sampler"] is not None:
            self.sampler.load_state_dict(state["sampler"])
        self.guard.load_state_dict(state["guard"])
        self.num_updates = state["num_updates"]
        self.obs_mean, self.obs_std = state["obs_mean"], state["obs_std"]
        self.target_returns = list(state["target_returns"])
        self.target_return = self.target_returns[0]
