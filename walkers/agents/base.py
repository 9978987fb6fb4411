"""The Agent interface: all the trainer, evaluator and checkpoints know about an algorithm.

An agent never sees Hydra, MLflow or the environment loop. It is built from plain
hyperparameters plus the environment's shapes (``obs_dim``, ``action_low``, ``action_high``),
and the trainer drives it with three calls per env step:

    action = agent.act(obs, explore=True)
    agent.observe(Transition(obs, action, reward, next_obs, terminated, truncated))
    losses = agent.update()        # {} when it is not time to learn (warm-up, mid-episode ...)

Offline agents (``offline = True``, e.g. the Decision Transformer) learn from a dataset instead:
the trainer calls only ``update`` in a loop. Sequence policies also see episode boundaries and
rewards while they act (``begin_episode``, ``record_reward``); the others ignore both.

Stable-Baselines3's twins (``impl=sb3``, :mod:`walkers.agents.sb3.twin`) learn inside SB3's
own loop: of this interface they act greedily (evaluations, videos) and checkpoint.

``update`` returns detached scalar tensors (not floats) so the hot loop never forces a
device sync; the trainer converts them only when it logs.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True, slots=True)
class Transition:
    obs: np.ndarray
    action: np.ndarray
    reward: float
    next_obs: np.ndarray
    terminated: bool  # the MDP ended: no bootstrapping from next_obs
    truncated: bool  # cut by a time limit: next_obs still has value

    @property
    def episode_over(self) -> bool:
        return self.terminated or self.truncated


class Agent(ABC):
    """Base for all algorithms. Subclasses keep their networks and optimizers as attributes."""

    device: torch.device
    offline: bool = False  # learns from a fixed dataset (``dataset=``), never from env steps

    def begin_episode(self) -> None:  # noqa: B027 (an optional hook)
        """A new episode starts (called by rollouts before the first ``act``)."""

    def record_reward(self, reward: float) -> None:  # noqa: B027 (an optional hook)
        """The reward the last ``act``'s action earned (called by rollouts)."""

    @abstractmethod
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """Action for one observation in the env's units; ``explore=False``: the greedy policy."""

    @abstractmethod
    def observe(self, transition: Transition) -> None:
        """Record one environment step."""

    @abstractmethod
    def update(self) -> dict[str, torch.Tensor]:
        """Learn from what was observed if it is time to; return named scalar diagnostics."""

    @abstractmethod
    def state_dict(self, with_buffer: bool = False) -> dict:
        """Everything needed to resume: networks, optimizers, counters, RNG states."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None: ...

    def resume_notes(self) -> dict[str, str]:
        """After :meth:`load_state_dict`: what the resumed agent could not restore exactly, as
        run tags (e.g. a replay buffer it has to refill); empty when the resume is exact."""
        return {}


def resolve_device(device: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)
