"""Stable-Baselines3 TD3 set up with a walkers TD3 config, for side-by-side benchmarks.

    python benchmarks/sb3_td3.py SPEC.json     # train one seed, as bench_learning.py does

SB3's TD3 defaults differ from the TD3 reference values walkers uses: learning rate 1e-3,
``learning_starts=100``, no exploration noise at all (``action_noise=None``) and 400-300
networks. :func:`make_model` sets every one of them from walkers' ``algo`` config instead, and
refuses options SB3 has no equivalent for. SB3 works in actions scaled to [-1, 1], so its noise
standard deviations are fractions of the action range's half-width, as walkers' are.

:class:`SB3Policy` puts a trained model behind the calls walkers' rollouts make, so one
evaluation function (:func:`walkers.training.rollout.run_episodes`) scores both libraries.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from stable_baselines3 import TD3
from stable_baselines3.common.noise import NormalActionNoise

from walkers.training.envs import make_env

#: walkers ActorCritic options SB3's TD3 cannot express, and the value that it can.
UNSUPPORTED = {
    "actor_lr": None,
    "critic_lr": None,
    "critic_hidden_sizes": None,
    "critic_architecture": "mlp",
    "noise_type": "gaussian",
    "population": 1,
    "compile": False,
}


def make_model(algo: dict, env, seed: int) -> TD3:
    """SB3 TD3 on ``env`` with the hyperparameters of walkers' ``algo`` config (a plain dict)."""
    for key, supported in UNSUPPORTED.items():
        if algo.get(key, supported) != supported:
            raise ValueError(f"algo.{key}={algo[key]!r} has no Stable-Baselines3 equivalent")
    act_dim = env.action_space.shape[0]
    noise = NormalActionNoise(np.zeros(act_dim), algo["exploration_noise"] * np.ones(act_dim))
    return TD3(
        "MlpPolicy",
        env,
        learning_rate=algo["lr"],
        buffer_size=algo["buffer_size"],
        learning_starts=algo["learning_starts"],  # uniform random actions, no updates
        batch_size=algo["batch_size"],
        tau=algo["tau"],
        gamma=algo["gamma"],
        train_freq=1,  # one gradient step per env step
        gradient_steps=1,
        action_noise=noise,  # SB3's default: none
        policy_delay=algo["policy_delay"],
        target_policy_noise=algo["policy_noise"],
        target_noise_clip=algo["noise_clip"],
        policy_kwargs={"net_arch": list(algo["hidden_sizes"]), "n_critics": 2},
        seed=seed,
        device="cpu",
    )


class SB3Policy:
    """A trained SB3 model behind the calls of :func:`walkers.training.rollout.run_episodes`."""

    def __init__(self, model: TD3):
        self.model = model

    def begin_episode(self) -> None:
        pass

    def record_reward(self, reward: float) -> None:
        pass

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        action, _ = self.model.predict(obs, deterministic=not explore)
        return action


def load_policy(path: Path) -> SB3Policy:
    return SB3Policy(TD3.load(path, device="cpu"))


def train(spec: dict) -> dict:
    """Train one seed as ``spec`` says; save the model; return the learning loop's timing."""
    torch.set_num_threads(spec["threads"])
    env = make_env(spec["env"])  # walkers' training env: same time limit, kwargs, shaping
    model = make_model(spec["algo"], env, spec["seed"])
    start = time.perf_counter()
    model.learn(total_timesteps=spec["total_steps"])
    seconds = time.perf_counter() - start
    model.save(spec["model_path"])
    env.close()
    return {"learn_s": seconds, "sps": spec["total_steps"] / seconds}


def main() -> None:
    spec_path = Path(sys.argv[1])
    result = train(json.loads(spec_path.read_text()))
    spec_path.with_suffix(".result.json").write_text(json.dumps(result))


if __name__ == "__main__":
    main()
