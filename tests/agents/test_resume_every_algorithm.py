"""Every declared algorithm resumes exactly: its state, round-tripped into a fresh agent built
from the same config, takes the same next steps as the agent it came from: the same actions,
the same losses, the same state after. One parametrised test over the declarations
(``SCHEMAS``), at each one's declared tiny settings: a new algorithm is covered by declaring it.

The snapshot is taken where nothing of an unfinished episode is pending (every 32 steps an
episode ends, a multiple of PPO's tiny rollout), so that what a resume deliberately starts anew
(PPO's and REINFORCE's episode in progress) is not in play; the global torch stream, which a
checkpoint keeps beside the agent, is set alike for both.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from hydra.utils import get_class

from tests.conftest import compose_cfg, tiny, tiny_offline_data
from tests.fingerprints import sha
from walkers.agents.base import Transition
from walkers.agents.declarations.schemas import SCHEMAS
from walkers.agents.factory import build_agent

EPISODE = 32  # steps
SPACES = {"obs_dim": 3, "action_low": [-2.0], "action_high": [2.0]}


def build(algo: str):
    cfg = compose_cfg([f"algo={algo}", "env=pendulum", "device=cpu", *tiny(algo)])
    offline = get_class(SCHEMAS[algo].AGENT).offline
    return build_agent(cfg, SPACES, **({"dataset": tiny_offline_data()} if offline else {}))


def steps(agent, start: int, n: int) -> list:
    """``n`` steps of a made-up task from step ``start`` (the same for any agent): what the agent
    did, each action and the losses of each update; offline, ``n`` gradient steps."""
    record = []
    for t in range(start, start + n):
        if agent.offline:
            losses = agent.update()
        else:
            rng = np.random.default_rng(t)
            obs = rng.normal(size=3).astype(np.float32)
            action = np.asarray(agent.act(obs, explore=True), dtype=np.float32)
            reward = float(-(obs**2).sum() - 0.1 * (action**2).sum())
            next_obs = rng.normal(size=3).astype(np.float32)
            end = (t + 1) % EPISODE == 0
            agent.observe(Transition(obs, action, reward, next_obs, False, end))
            losses = agent.update()
            record.append(action.tolist())
        record.append({k: v.detach().cpu().tolist() for k, v in losses.items()})
    return record


@pytest.mark.parametrize("algo", sorted(SCHEMAS))
def test_a_restored_agent_takes_the_same_next_steps(algo):
    agent = build(algo)
    before = 256 if not agent.offline else 4  # past every warm-up, several updates in
    torch.manual_seed(1)
    steps(agent, 0, before)
    state = copy.deepcopy(agent.state_dict(with_buffer=True))
    twin = build(algo)
    twin.load_state_dict(state)
    assert twin.resume_notes() == {}, "the round trip lost something it had to restart"
    after = 128 if not agent.offline else 3  # a PPO rollout, several off-policy updates
    torch.manual_seed(2)
    original = steps(agent, before, after)
    torch.manual_seed(2)
    restored = steps(twin, before, after)
    assert any(losses for losses in original if isinstance(losses, dict)), "nothing was learned"
    assert restored == original
    assert sha(twin.state_dict(with_buffer=True)) == sha(agent.state_dict(with_buffer=True))
