"""TD3+BC (Fujimoto & Gu 2021, "A Minimalist Approach to Offline Reinforcement Learning"):
TD3 trained offline on a fixed dataset, with a behaviour-cloning term in the actor's loss.

The paper's Algorithm 1 is TD3's (:mod:`walkers.agents.td3`, whose :meth:`~TD3.update` this
class runs as it is), on the dataset's transitions instead of a growing replay buffer, with two
changes:

    s <- (s - mu) / (sigma + 1e-3), mu, sigma: the dataset's state mean, std  (_attach; acting)
    lambda = alpha / (N^-1 sum |Q_1(s_i, pi(s_i))|)   (a constant, no gradient) (actor_loss)
    pi = argmax N^-1 sum [lambda Q_1(s_i, pi(s_i)) - (pi(s_i) - a_i)^2]        (actor_loss)

The critics' update (clipped double Q, target policy smoothing, delayed actor and targets) is
TD3's unchanged. lambda keeps the Q term at the scale of the BC term whatever the rewards'
scale; alpha (2.5) trades the two off. The states are normalized in the buffer (s and s') and
wherever the agent acts; the mean and std go into its checkpoints, so an evaluation or a
dataset recorded from it needs no dataset. It never explores: acting is pi(normalized s).

Offline, ``total_steps``, ``eval_every`` and ``checkpoint_every`` count gradient steps. The
dataset itself is not checkpointed: a resumed run reloads it by name, as a Decision
Transformer's does (:mod:`walkers.agents.dt`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from walkers.agents.td3 import TD3
from walkers.data.replay import Batch

STD_EPS = 1e-3  # added to the dataset's state std (the reference code's)


class TD3BC(TD3):
    """Hyperparameters: TD3's (lr, batch_size, ..., policy_delay) with ``alpha`` and
    ``normalize_states``, declared with the reference defaults in
    :mod:`walkers.agents.declarations.schemas`. No warm-up, no exploration noise, one member: the
    buffer is the dataset."""

    offline = True
    trains_populations = False  # one member: the buffer is the dataset

    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        dataset=None,  # walkers.data.datasets.OfflineData; None when only restoring a policy to act
        alpha: float,
        normalize_states: bool,
        **td3,
    ):
        dataset_size = dataset.steps if dataset is not None else 0
        super().__init__(
            obs_dim,
            action_low,
            action_high,
            exploration_noise=0.0,
            learning_starts=0,
            buffer_size=max(dataset_size, 1),
            **td3,
        )
        self.alpha, self.normalize_states = float(alpha), bool(normalize_states)
        self.dataset_size = dataset_size
        self.obs_mean = np.zeros(obs_dim, dtype=np.float32)
        self.obs_std = np.ones(obs_dim, dtype=np.float32)
        if dataset is not None:
            self._attach(dataset)

    def _attach(self, dataset) -> None:
        """The dataset's transitions, states normalized, as the (full) replay buffer."""
        if self.dataset_size < self.batch_size:
            raise ValueError(
                f"batch_size={self.batch_size} is more than the {self.dataset_size} transitions "
                f"of dataset {dataset.id!r}"
            )
        episodes = dataset.episodes
        obs = np.concatenate([e.observations[:-1] for e in episodes])
        if self.normalize_states:
            self.obs_mean = obs.mean(axis=0).astype(np.float32)
            self.obs_std = (obs.std(axis=0) + STD_EPS).astype(np.float32)
        transitions = {
            "obs": self.normalize(obs),
            "action": np.concatenate([e.actions for e in episodes]),
            "reward": np.concatenate([e.rewards for e in episodes]),
            "next_obs": self.normalize(np.concatenate([e.observations[1:] for e in episodes])),
            "terminated": np.concatenate([e.terminations for e in episodes]),
        }
        self.buffer.hold_dataset(
            {k: torch.as_tensor(v, dtype=torch.float32) for k, v in transitions.items()}
        )

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        return (obs - self.obs_mean) / self.obs_std

    # --- acting: pi(normalized s), never noise ---------------------------------------------------
    def act_population(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """pi of the normalized states; ``explore`` is ignored (offline, nothing explores)."""
        return super().act_population(self.normalize(obs), explore=False)

    def store_steps(self, *steps) -> None:
        """Offline: the agent learns from its dataset and is never shown a step."""
        raise NotImplementedError("TD3BC learns offline: it observes nothing")

    # --- learning: TD3's update, with this actor loss ---------------------------------------------
    def actor_loss(self, b: Batch) -> torch.Tensor:
        """-lambda N^-1 sum Q_1(s, pi(s)) + N^-1 sum (pi(s) - a)^2 per member ``(K,)``, lambda =
        alpha / N^-1 sum |Q_1(s, pi(s))| detached; the squared error averaged over the action's
        dimensions too (the reference's ``F.mse_loss``)."""
        action = self.actor(b.obs)
        q_pi = self.q1(b.obs, action)
        lmbda = self.alpha / q_pi.abs().mean(dim=-1).detach()
        behaviour_cloning = (action - b.action).pow(2).mean(dim=(1, 2))
        return -lmbda * q_pi.mean(dim=-1) + behaviour_cloning

    # --- checkpoints: the normalization, never the dataset ---------------------------------------
    def state_dict(self, with_buffer: bool = False) -> dict:
        """TD3's (the buffer's sampler state, not its transitions) and the normalization."""
        return super().state_dict(with_buffer=False) | {
            "obs_mean": self.obs_mean,
            "obs_std": self.obs_std,
        }

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.obs_mean, self.obs_std = state["obs_mean"], state["obs_std"]

    def refill_if_lost(self, buffer_state: dict) -> None:
        """Nothing to refill: the buffer holds the dataset, reloaded by name (a checkpoint holds
        only its sampler's state)."""
