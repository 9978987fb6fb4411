"""A seed population's members one at a time: cut out as single agents, loaded back, acting alone.

An :class:`~walkers.agents.common.actor_critic.ActorCritic` with ``population=K`` holds K members
along the leading dimension of every network, optimizer moment and guard counter (the critics C per
member; which parts, and each member's slice of them, the agent declares in ``member_cuts``), and a
:class:`Member` each (its RNG, exploration noise and replay buffer). A single agent is the same with
K = 1, so member ``i`` cut out (:func:`member_state_dict`) is exactly a single agent's
``state_dict()``, and a population's is the list of its members'. A member's state loads into an
ordinary agent (``walkers.evaluate``, ``walkers.collect``, ``resume=`` to continue it alone) or back
into a population (:func:`load_member_state_dict`, ``resume=[id,id,...]``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from walkers.agents.base import Policy
from walkers.agents.common.health import NonFiniteGuard
from walkers.data.replay import ReplayBuffer
from walkers.seeding import RandomStreams


class Population(Protocol):
    """What member I/O needs of an agent with members (an
    :class:`~walkers.agents.common.actor_critic.ActorCritic`, which imports this module)."""

    members: list  # of actor_critic.Member
    buffer: ReplayBuffer
    update_noise: RandomStreams
    guard: NonFiniteGuard
    actor: torch.nn.Module
    device: torch.device

    def member_cuts(self, i: int) -> dict[str, slice]: ...

    def load_counters(self, state: dict) -> None: ...

    def refill_if_lost(self, buffer_state: dict) -> None: ...

    def resume_notes(self) -> dict[str, str]: ...


ADAM_MOMENTS = ("exp_avg", "exp_avg_sq")


def member_state_dict(agent: Population, i: int, with_buffer: bool = False) -> dict:
    """Member ``i`` of ``agent`` as a single agent's ``state_dict()``: its slice of every
    per-member part (``agent.member_cuts``: networks, targets, Adam moments, ...), its RNG,
    noise, buffer and guard counters; the shared counters."""
    state = {}
    for name, cut in agent.member_cuts(i).items():
        part = getattr(agent, name)
        if isinstance(part, torch.optim.Optimizer):
            optimizer_state = part.state_dict()
            for index, moments in list(optimizer_state["state"].items()):
                # a new dict: state_dict() shares the live tensors
                sliced = {key: moments[key][cut].clone() for key in ADAM_MOMENTS}
                optimizer_state["state"][index] = moments | sliced
            state[name] = optimizer_state
        else:
            state[name] = {k: v[cut].clone() for k, v in part.state_dict().items()}
    shared = ("steps", "num_updates", "random_until", "update_after")
    return state | {
        **{key: getattr(agent, key) for key in shared},
        **agent.members[i].state_dict(),  # rng, noise
        "buffer": agent.buffer.member_state_dict(i, with_buffer),
        "update_noise": agent.update_noise.member_state_dict(i),
        "guard": agent.guard.member_state_dict(i),
    }


@torch.no_grad()
def load_member_state_dict(agent: Population, i: int, state: dict) -> None:
    """Load a single agent's ``state_dict()`` into member ``i`` of ``agent``.

    Counters (env steps, updates, Adam's step count) are shared, so every member must be at the
    same update (``walkers.train`` checks); they are taken from the last member loaded.
    """
    for name, cut in agent.member_cuts(i).items():
        part = getattr(agent, name)
        if isinstance(part, torch.optim.Optimizer):
            _load_optimizer_member(part, cut, state[name]["state"])
        else:
            for key, value in part.state_dict().items():
                value[cut] = state[name][key]
    agent.load_counters(state)
    agent.members[i].load_state_dict(state)
    agent.buffer.load_member_state_dict(i, state["buffer"])
    if "update_noise" in state:  # saved before the update's noise had streams of its own
        agent.update_noise.load_member_state_dict(i, state["update_noise"])
    agent.guard.load_member_state_dict(i, state["guard"])
    agent.refill_if_lost(state["buffer"])


def _load_optimizer_member(optimizer: torch.optim.Optimizer, cut: slice, saved_state: dict):
    """A member's Adam moments (``saved_state``: its optimizer ``state_dict()["state"]``) into
    the ``cut`` of ``optimizer``'s."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for index, param in enumerate(params):  # the indices of optimizer.state_dict()
        if index not in saved_state:
            continue  # the member never stepped this parameter
        saved, live = saved_state[index], optimizer.state[param]
        if not live:  # a fresh optimizer: create its state as its first step would
            live["step"] = saved["step"].clone().to(param.device)
            live |= {key: torch.zeros_like(param) for key in ADAM_MOMENTS}
        for key in ADAM_MOMENTS:
            live[key][cut] = saved[key].to(param.device)
        live["step"].copy_(saved["step"])


class MemberAgent(Policy):
    """Member ``index`` of a population seen as an agent of its own: it acts greedily
    (evaluations) and checkpoints as a single agent; the population does the learning."""

    def __init__(self, population: Population, index: int):
        self.population, self.index = population, index
        self.members = slice(index, index + 1)
        self.device = population.device

    def act(self, obs: np.ndarray, explore: bool = False) -> np.ndarray:
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            action = self.population.actor(obs_t.view(1, 1, -1), members=self.members)[0, 0]
        return action.cpu().numpy().astype(np.float32)

    def state_dict(self, with_buffer: bool = False) -> dict:
        return member_state_dict(self.population, self.index, with_buffer)

    def load_state_dict(self, state: dict) -> None:
        load_member_state_dict(self.population, self.index, state)

    def resume_notes(self) -> dict[str, str]:
        return self.population.resume_notes()
