"""Seeded fingerprints of every agent: the proof that a restructuring changed no behaviour.

    python -m tests.fingerprints > before.json     # on the old code
    python -m tests.fingerprints --check before.json   # on the new: exits 1 on any difference

Each agent is built from its real config (conf/algo, small networks), driven by a real env for
``STEPS`` steps (act with exploration, step, observe, update), and fingerprinted: the greedy
actions on fixed observations, every weight and optimizer moment of its checkpoint, and the
explored actions along the way, each as a sha256 of the exact bytes. Same code, same seed: same
fingerprint; any change in the math, the order of random draws or the state layout shows.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys

import numpy as np
import torch

from tests.conftest import ONLINE, compose_cfg, tiny
from walkers.agents.base import Transition
from walkers.agents.factory import build_agent
from walkers.training.envs import env_spaces, make_env

STEPS = 400
#: every online algorithm at its declared tiny settings, and the variants that take other paths
CASES = {name: [f"algo={name}", *tiny(name)] for name in ONLINE} | {
    "td3_population2": ["algo=td3", "population=2", *tiny("td3")],
    "ddpg_ou_layernorm": [
        "algo=ddpg",
        "algo.noise_type=ou",
        "algo.critic_architecture=layernorm_branch",
        "algo.critic_hidden_sizes=[40,30]",
        *tiny("ddpg"),
    ],
    "crossq_population2": ["algo=crossq", "population=2", *tiny("crossq")],
}


def _digest(value, h) -> None:
    """Feed ``value`` (nested dicts/lists of tensors, arrays and scalars) into ``h``, in a fixed
    order."""
    if isinstance(value, dict):
        for key in sorted(value, key=str):
            h.update(str(key).encode())
            _digest(value[key], h)
    elif isinstance(value, list | tuple):
        for item in value:
            _digest(item, h)
    elif isinstance(value, torch.Tensor):
        h.update(value.detach().cpu().contiguous().numpy().tobytes())
    elif isinstance(value, np.ndarray):
        h.update(np.ascontiguousarray(value).tobytes())
    else:
        h.update(repr(value).encode())


def sha(value) -> str:
    h = hashlib.sha256()
    _digest(value, h)
    return h.hexdigest()[:16]


def fingerprint(overrides: list[str]) -> dict[str, str]:
    cfg = compose_cfg(["env=pendulum", "device=cpu", "seed=3", *overrides])
    k = cfg.population
    envs = [make_env(cfg.env) for _ in range(k)]
    agent = build_agent(cfg, env_spaces(envs[0]), **({"population": k} if k > 1 else {}))
    obs = np.stack([env.reset(seed=10 + i)[0] for i, env in enumerate(envs)])
    explored, losses = [], []
    for _ in range(STEPS):
        if k > 1:
            actions = agent.act_population(obs, explore=True)
        else:
            actions = agent.act(obs[0], explore=True)[None]
        explored.append(actions)
        transitions = []
        for i, env in enumerate(envs):
            next_obs, reward, terminated, truncated, _ = env.step(actions[i])
            transitions.append(
                Transition(obs[i], actions[i], float(reward), next_obs, terminated, truncated)
            )
            obs[i] = env.reset()[0] if terminated or truncated else next_obs
        if k > 1:
            agent.observe_population(transitions)
        else:
            agent.observe(transitions[0])
        losses.append(agent.update())
    probe = np.random.default_rng(0).normal(size=(8, envs[0].observation_space.shape[0]))
    if k > 1:
        greedy = [agent.act_population(np.repeat(o[None], k, 0), explore=False) for o in probe]
    else:
        greedy = [agent.act(o.astype(np.float32), explore=False) for o in probe]
    return {
        "explored_actions": sha(explored),
        "losses": sha(losses),
        "greedy_actions": sha(greedy),
        "checkpoint": sha(agent.state_dict()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", help="a fingerprints file to compare with")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    prints = {name: fingerprint(overrides) for name, overrides in CASES.items()}
    if not args.check:
        print(json.dumps(prints, indent=2))
        return 0
    before = json.loads(open(args.check).read())
    differ = [
        f"{name}.{part}"
        for name in CASES
        if name in before  # a case the file does not have is new, not different
        for part in prints[name]
        if before[name].get(part) != prints[name][part]
    ]
    for name in CASES:
        if name not in before:
            status = "new (not in the file)"
        else:
            status = "DIFFERS" if any(d.startswith(name + ".") for d in differ) else "identical"
        print(f"{name:<20} {status}")
    if differ:
        print("differ: " + ", ".join(differ))
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
