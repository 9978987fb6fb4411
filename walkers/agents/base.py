"""The Policy and Agent interfaces: all the trainer, evaluator and checkpoints know about an
algorithm. A :class:`Policy` acts and checkpoints; an :class:`Agent` is a policy that learns.

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
own loop, and a population's member (:class:`~walkers.agents.common.actor_critic.MemberAgent`)
through its population: both are policies, acting greedily (evaluations, videos) and
checkpointing.

What the trainer may ask beyond that, each class declares (:class:`Policy`'s flags), and nothing
probes for methods: ``offline``, ``trains_populations``, ``several_envs``,
``return_conditioned``, ``trains_itself``.

``update`` returns detached scalar tensors (not floats) so the hot loop never forces a
device sync; the trainer converts them only when it logs.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

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


class Policy(ABC):
    """What acts: greedy or exploring actions, episode hooks, checkpoints; and what the class
    declares it can do beyond that (the flags, read by the trainer and the config checks)."""

    device: torch.device
    #: learns from a fixed dataset (``dataset=``), never from env steps
    offline: bool = False
    #: trains K seeds in one agent (``population=K``: ``act_population``,
    #: ``observe_population``, ``member_policy``)
    trains_populations: bool = False
    #: acts on several envs' observations as one batch (``observe_batch``; ``num_envs``)
    several_envs: bool = False
    #: acts toward a target return (``target_return``, ``target_returns``)
    return_conditioned: bool = False
    #: learns inside its own library's loop (SB3's twins): the trainer only watches it
    trains_itself: bool = False

    def begin_episode(self) -> None:  # noqa: B027 (an optional hook)
        """A new episode starts (called by rollouts before the first ``act``)."""

    def record_reward(self, reward: float) -> None:  # noqa: B027 (an optional hook)
        """The reward the last ``act``'s action earned (called by rollouts)."""

    @abstractmethod
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """Action for one observation in the env's units; ``explore=False``: the greedy policy."""

    @abstractmethod
    def state_dict(self, with_buffer: bool = False) -> dict:
        """Everything needed to resume: networks, optimizers, counters, RNG states."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None: ...

    def resume_notes(self) -> dict[str, str]:
        """After :meth:`load_state_dict`: what the resumed agent could not restore exactly, as
        run tags (e.g. a replay buffer it has to refill); empty when the resume is exact."""
        return {}


class Agent(Policy):
    """A policy that learns: every algorithm. Subclasses keep their networks and optimizers as
    attributes."""

    def observe(self, transition: Transition) -> None:
        """Record one environment step (an online agent; an offline one learns from its dataset
        and is never shown one)."""
        raise NotImplementedError(f"{type(self).__name__} learns offline: it observes nothing")

    @abstractmethod
    def update(self) -> dict[str, torch.Tensor]:
        """Learn from what was observed (online) or from the dataset (offline) if it is time
        to; return named scalar diagnostics."""


def resolve_device(device: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


#: ``algo.precision``: the dtype an agent's learning runs in under autocast (None: plain fp32)
PRECISIONS = {"fp32": None, "bf16": torch.bfloat16}
#: CPU flags of native bfloat16 matmuls (x86): without one, bf16 autocast is emulated and slow
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def autocast(device: torch.device, precision: str):
    """The context an agent learns in: bfloat16 autocast for ``bf16`` (matmuls and attention in
    bfloat16, reductions, LayerNorm, the weights and the optimizer in fp32), nothing for
    ``fp32``. Without autocast's cache of cast weights, which a CUDA graph's capture (an update
    under ``capture``) must not hold: each weight is cast where it is used."""
    dtype = PRECISIONS[precision]
    return torch.autocast(
        device.type, dtype=dtype or torch.float32, enabled=dtype is not None, cache_enabled=False
    )


def cpu_has_native_bf16(cpuinfo: str | None = None) -> bool | None:
    """Whether this CPU multiplies bfloat16 natively (``/proc/cpuinfo``'s flags, or ``cpuinfo``
    given); None where that cannot be told (not Linux, not x86)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return None
    lines = [line for line in cpuinfo.splitlines() if line.startswith("flags")]
    if not lines:  # not x86 (an ARM CPU lists "Features"): unknown here, so no warning
        return None
    flags = {f for line in lines for f in line.split()}
    return any(flag in flags for flag in NATIVE_BF16_FLAGS)


def warn_if_slow_precision(device: torch.device, precision: str) -> None:
    """bf16 on a CPU without native bfloat16 matmuls is emulated: measured 10.7x slower a DT step
    than fp32 on an AMD EPYC without AVX-512 BF16 (1.57x faster on one with it). Say so once,
    at the start of the run, rather than let a user wait."""
    if precision == "bf16" and device.type == "cpu" and cpu_has_native_bf16() is False:
        logging.getLogger("walkers").warning(
            "algo.precision=bf16 on a CPU without %s: bfloat16 is emulated here, about 10x "
            "slower than fp32 (algo.precision=fp32)",
            " or ".join(NATIVE_BF16_FLAGS),
        )
