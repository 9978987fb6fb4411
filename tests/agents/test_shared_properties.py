"""What every off-policy algorithm promises, tested once, for each one the declarations name (as
the fingerprints and the resume round trip are: a new algorithm is covered with no edit here):

- ``compile=true`` computes the same updates as the eager code;
- a NaN in one member's data stays in that member (the guard skips its update, the others learn
  on as if it were not there);
- member k of a population updates as the single agent of seed k would.

The resume round trip of every declared algorithm is ``test_resume_every_algorithm.py``'s."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from hydra.utils import get_class

from tests.conftest import feed_members, filled_agent
from walkers.agents.base import Transition
from walkers.agents.declarations.schemas import SCHEMAS
from walkers.agents.factory import defaults_for

#: the algorithms that train seed populations (one batched update for K seeds)
POPULATIONS = sorted(
    name for name, schema in SCHEMAS.items() if get_class(schema.AGENT).trains_populations
)
#: the algorithms that declare ``compile``
COMPILED = sorted(
    name
    for name, schema in SCHEMAS.items()
    if "compile" in {f.name for f in dataclasses.fields(schema)}
    and not getattr(get_class(schema.AGENT), "offline", False)
)
OBS = 3


def agent_class(name: str):
    return get_class(SCHEMAS[name].AGENT)


def tiny(name: str, **settings) -> dict:
    """The algorithm's declared tiny settings, a small buffer and warm-up, and ``settings``."""
    small = {"batch_size": 16, "learning_starts": 20, "buffer_size": 1000}
    return SCHEMAS[name].TINY | small | settings


def per_member_parts(agent, member: int) -> dict[str, torch.Tensor]:
    """Member ``member``'s slice of every per-member module (weights, targets, a temperature,
    running statistics), by name: the parts its checkpoint holds (``member_cuts``)."""
    parts = {}
    for name, cut in agent.member_cuts(member).items():
        module = getattr(agent, name)
        if not isinstance(module, torch.nn.Module):
            continue  # an optimizer: its moments follow the weights
        whole = agent.population * (cut.stop - cut.start)
        for key, value in module.state_dict().items():
            if value.dim() > 0 and value.shape[0] == whole:
                parts[f"{name}.{key}"] = value[cut]
    return parts


# --- compile = eager ------------------------------------------------------------------------------
def rounding_tolerance(name: str, agent, key: str) -> dict:
    """How near a compiled update must come to the eager one, or a member to the single agent of
    its seed (``key``: a part, or "" for the update's metrics). Float32 sums in another order:
    assert_close's defaults, except where a quantity is rounding noise to begin with:

    - TD7: its three losses chain through an encoder and hard target copies (1e-4 relative);
    - CrossQ: a hidden unit active on the whole batch, followed by a batch renormalization, has
      a bias whose exact gradient is zero (the normalization removes any shift); its computed
      gradient is rounding noise, which Adam's sign-like early steps turn into +-lr moves that
      differ between the two sums. Those biases are held to Adam's bound over the updates.
    """
    if name == "td7":
        return {"rtol": 1e-4, "atol": 1e-5}
    if name != "crossq":
        return {}
    module = key.split(".")[0]
    renormalized = (
        key.endswith(".bias")
        and ".layers." in key
        and not key.startswith(f"{module}.layers.{len(getattr(agent, module).layers) - 1}.")
    )
    if not renormalized:
        return {"rtol": 1e-3, "atol": 1e-4}
    lr = getattr(agent, f"{module}_optimizer").param_groups[0]["lr"]
    return {"rtol": 0, "atol": 6 * lr}


@pytest.mark.parametrize("name", COMPILED)
def test_compiled_updates_follow_the_eager_ones(name):
    """Two members (a single agent is a population of one: the same code, K = 1)."""
    cls, population = agent_class(name), 2
    settings = SCHEMAS[name].TINY | {"hidden_sizes": [32, 32], "batch_size": 32}
    eager = filled_agent(cls, population, **settings)
    compiled = filled_agent(cls, population, compile=True, **settings)
    start = per_member_parts(filled_agent(cls, population, **settings), 0)
    for _ in range(6):  # TD3's delayed actor step twice and more; TD7's hard copies
        torch.manual_seed(0)  # the same global draws for both, where an update makes any
        expected = eager.update()
        torch.manual_seed(0)
        got = compiled.update()
        assert set(got) == set(expected)
        for key, value in expected.items():
            torch.testing.assert_close(
                got[key], value, msg=key, **rounding_tolerance(name, eager, "")
            )
    for member in range(population):
        mine = per_member_parts(compiled, member)
        for key, value in per_member_parts(eager, member).items():
            tolerance = rounding_tolerance(name, eager, key)
            torch.testing.assert_close(mine[key], value, msg=key, **tolerance)
    moved = [not torch.equal(v, start[k]) for k, v in per_member_parts(compiled, 0).items()]
    assert any(moved)  # it compares learning, not two idle agents


# --- a NaN stays in its member --------------------------------------------------------------------
@pytest.mark.parametrize(
    "name,compiled",
    [(name, False) for name in POPULATIONS] + [("td3", True)],  # TD3 whole, compiled on the CPU
)
def test_a_nan_stays_in_its_member(name, compiled):
    cls = agent_class(name)
    settings = tiny(name, compile=True) if compiled else tiny(name)

    def trained(rewards):
        agent = cls(OBS, [-2.0], [2.0], population=2, seed=0, **defaults_for(cls, **settings))
        feed_members(agent, rewards=rewards, terminate_every=37)
        return agent

    clean, poisoned = trained((1.0, -1.0)), trained((1.0, float("nan")))  # member 1: NaN rewards
    assert clean.num_updates > 30
    for member in (0, 1):
        for key, value in per_member_parts(poisoned, member).items():
            assert torch.isfinite(value).all(), (member, key)  # no NaN entered any weight
    mine = per_member_parts(clean, 0)
    for key, value in per_member_parts(poisoned, 0).items():
        assert torch.equal(value, mine[key]), key  # member 0 never felt member 1's data
    assert poisoned.guard.skipped[0].item() == 0 and poisoned.guard.skipped[1].item() > 0


# --- member k = seed k ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", POPULATIONS)
def test_a_member_updates_as_the_single_agent_of_its_seed(name):
    """Member 1 of seeds (5, 6) against seed 6 alone, fed the same transitions: the same
    initial weights, batches and noise, so the same losses and parts after 60 updates, to float
    rounding (the members' sums run batched)."""
    cls = agent_class(name)
    small = defaults_for(cls, **tiny(name, learning_starts=0, buffer_size=500))
    pair = cls(OBS, [-2.0], [2.0], population=2, seed=5, **small)
    alone = cls(OBS, [-2.0], [2.0], population=1, seed=6, **small)
    rng = np.random.default_rng(0)
    for t in range(200):
        obs, nxt, other, other_next = rng.normal(size=(4, OBS)).astype(np.float32)
        action, reward = rng.uniform(-2, 2, 1).astype(np.float32), float(rng.normal())
        mine = Transition(obs, action, reward, nxt, t % 50 == 49, False)
        pair.observe_population([Transition(other, action, reward, other_next, False, False), mine])
        alone.observe(mine)
    for _ in range(60):
        together, single = pair.update(), alone.update()
        assert together["loss/critic"][1].item() == pytest.approx(
            single["loss/critic"][0].item(), rel=1e-4, abs=1e-6
        )
    ours = per_member_parts(alone, 0)
    for key, value in per_member_parts(pair, 1).items():
        # CrossQ's rounding-noise gradients (rounding_tolerance) part the two on some CPUs
        # (AVX-512's sums: its renormalized actor's first layer 5e-4 apart after 60 updates)
        crossq = name == "crossq"
        tolerance = rounding_tolerance(name, alone, key) if crossq else {"rtol": 1e-4, "atol": 1e-5}
        torch.testing.assert_close(value, ours[key], msg=key, **tolerance)
