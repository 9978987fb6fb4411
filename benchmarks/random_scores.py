"""The random-policy score of each env (the floor of its normalized score in ``conf/env/``).

    python benchmarks/random_scores.py [--episodes 100] [--envs walker2d,hopper]

Uniform random actions, the env's own reward and time limit, episodes from independent start
states (seed 0..episodes-1); prints a table of the mean, its standard error and the episodes.
"""

from __future__ import annotations

import argparse

import numpy as np
import yaml

from walkers import CONF_DIR
from walkers.training.envs import make_env

ENVS = "walker2d,hopper,half_cheetah,ant,humanoid,bipedal_walker,pendulum,inverted_pendulum"


def random_return(env_name: str, episodes: int) -> tuple[float, float]:
    env_cfg = yaml.safe_load((CONF_DIR / "env" / f"{env_name}.yaml").read_text())
    env = make_env(env_cfg, shaping=False)
    env.action_space.seed(0)
    returns = []
    for episode in range(episodes):
        env.reset(seed=episode)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    env.close()
    return float(np.mean(returns)), float(np.std(returns, ddof=1) / np.sqrt(episodes))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--envs", default=ENVS)
    args = parser.parse_args()
    print("| env | random return, mean | standard error | episodes |\n|---|---|---|---|")
    for name in args.envs.split(","):
        mean, se = random_return(name, args.episodes)
        print(f"| {name} | {mean:.2f} | {se:.2f} | {args.episodes} |", flush=True)


if __name__ == "__main__":
    main()
