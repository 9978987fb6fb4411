"""How a run is evaluated: greedy episodes from the run's start states, or, for a
return-conditioned agent (the Decision Transformer), greedy episodes per target return.

The greedy episodes themselves (:func:`run_episodes`, a population's together
:func:`run_population_episodes`, with frames :func:`record_episodes`) are played here for the
trainer, ``walkers.evaluate`` and ``walkers.collect`` alike."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from walkers.agents.base import Agent
from walkers.metrics import normalized_score

#: (agent, eval env, start seeds) -> (returns of the headline evaluation, extra metrics)
Evaluation = Callable[[Agent, gym.Env, list[int]], tuple[np.ndarray, dict[str, float]]]
#: A return -> its normalized score (0: a random policy, 100: the expert reference), or None.
Normalize = Callable[[float], float | None]


def run_episodes(
    agent: Agent,
    env: gym.Env,
    start_seeds: Sequence[int],
    on_frame: Callable[[int, np.ndarray], None] | None = None,
    render_episodes: int | None = None,
) -> np.ndarray:
    """Returns of one greedy episode per start seed; episode ``i`` starts from
    ``reset(seed=start_seeds[i])`` (a run's are :func:`walkers.seeding.eval_start_seeds`).

    Seeding every episode makes a run's evaluations comparable across its checkpoints (the same
    start states each time). ``on_frame(episode, frame)`` receives the rendered frames of the
    first ``render_episodes`` episodes (all when None); the env needs ``render_mode="rgb_array"``.
    """
    returns = np.zeros(len(start_seeds))
    for i, start_seed in enumerate(start_seeds):
        obs, _ = env.reset(seed=int(start_seed))
        agent.begin_episode()
        render = on_frame is not None and (render_episodes is None or i < render_episodes)
        done = False
        while not done:
            if render:
                on_frame(i, env.render())
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, explore=False))
            agent.record_reward(float(reward))
            returns[i] += reward
            done = terminated or truncated
    return returns


def run_population_episodes(
    population, envs: Sequence[gym.Env], start_seeds: Sequence[Sequence[int]]
) -> np.ndarray:
    """``(K, episodes)`` returns of a population's K members' greedy episodes, member k's
    episode j from ``envs[k].reset(seed=start_seeds[k][j])``, as :func:`run_episodes` plays
    them one member at a time; here the K members' j-th episodes play together, one batched
    greedy forward of all members a step (``act_population``: the forward their training acts
    through), a member whose episode is over waiting for the others."""
    k, episodes = len(envs), len(start_seeds[0])
    returns = np.zeros((k, episodes))
    for j in range(episodes):
        starts = zip(envs, start_seeds, strict=True)
        obs = np.stack([env.reset(seed=int(seeds[j]))[0] for env, seeds in starts])
        playing = list(range(k))
        while playing:
            actions = population.act_population(obs, explore=False)
            still = []
            for i in playing:
                obs[i], reward, terminated, truncated, _ = envs[i].step(actions[i])
                returns[i, j] += reward
                if not (terminated or truncated):
                    still.append(i)
            playing = still
    return returns


def record_episodes(
    agent: Agent, env: gym.Env, start_seeds: Sequence[int], render_episodes: int = 1
) -> tuple[np.ndarray, list[np.ndarray], float]:
    """:func:`run_episodes` keeping the first ``render_episodes``: (returns, frames, fps)."""
    frames: list[np.ndarray] = []
    returns = run_episodes(
        agent, env, start_seeds, lambda _, frame: frames.append(frame), render_episodes
    )
    return returns, frames, env.metadata.get("render_fps") or 30


@dataclass(frozen=True)
class References:
    """The two returns an offline run's normalized score 100 x (R - random) / (expert - random)
    is measured between. ``source`` says where they come from: ``env`` (``scores.random`` and
    ``scores.expert`` of ``conf/env/<env>.yaml``, measured by the platform once for every dataset
    of the env, so that scores on different datasets compare, as D4RL's do) or ``dataset`` (a
    random policy's and the behaviour policy's mean returns, measured when it was recorded)."""

    random: float | None
    expert: float | None
    source: str

    def normalized(self, episode_return: float) -> float | None:
        """The normalized score of ``episode_return``; None without both references."""
        if self.random is None or self.expert is None or self.expert == self.random:
            return None
        return normalized_score(episode_return, self.random, self.expert)

    def as_params(self) -> dict[str, object]:
        return {
            "normalized_score.random": self.random,
            "normalized_score.expert": self.expert,
            "normalized_score.references": self.source,
        }


def offline_references(env_cfg, data) -> References:
    """The env's references where ``conf/env`` has both, else the dataset's own."""
    scores = env_cfg.get("scores") or {}
    if scores.get("random") is not None and scores.get("expert") is not None:
        return References(float(scores["random"]), float(scores["expert"]), "env")
    return References(data.random_return, data.behaviour_return, "dataset")


def greedy_evaluation(agent: Agent, env: gym.Env, start_seeds: list[int]):
    """Deterministic episodes, one per start seed."""
    return run_episodes(agent, env, start_seeds), {}


class PopulationEvaluation:
    """A population's evaluations, all K members' greedy episodes played together
    (:func:`run_population_episodes`), each member's book
    reading its own: :meth:`of_member` is member i's :data:`Evaluation`. The first book to ask
    at a step plays them; the others read what it played (the population's ``steps`` count says
    which step that was)."""

    def __init__(self, population, envs: Sequence[gym.Env], start_seeds: Sequence[Sequence[int]]):
        self.population, self.envs, self.start_seeds = population, envs, start_seeds
        self._played_at: int | None = None
        self._returns: np.ndarray | None = None

    def of_member(self, i: int) -> Evaluation:
        def evaluate(agent, env: gym.Env, start_seeds: list[int]):
            if self._played_at != self.population.steps:
                self._returns = run_population_episodes(
                    self.population, self.envs, self.start_seeds
                )
                self._played_at = self.population.steps
            return self._returns[i], {}

        return evaluate


def per_target_return(normalize: Normalize) -> Evaluation:
    """Greedy episodes for each of ``agent.target_returns``: the first target is the headline
    (``eval/return_mean``); every target is also logged on its own
    (``eval/target_<R>/return_mean``) and, where the dataset has reference returns, as a
    normalized score (``.../normalized_score``, and ``eval/normalized_score`` for the first;
    :func:`offline_references`)."""

    def evaluate(agent, env: gym.Env, start_seeds: list[int]):
        extra, headline = {}, None
        for target in agent.target_returns:
            agent.target_return = target
            returns = run_episodes(agent, env, start_seeds)
            name = f"eval/target_{target:g}"
            extra[f"{name}/return_mean"] = float(returns.mean())
            if (score := normalize(float(returns.mean()))) is not None:
                extra[f"{name}/normalized_score"] = score
            headline = returns if headline is None else headline
        agent.target_return = agent.target_returns[0]
        if (score := normalize(float(headline.mean()))) is not None:
            extra["eval/normalized_score"] = score
        return headline, extra

    return evaluate


def scored_greedy(normalize: Normalize) -> Evaluation:
    """Greedy episodes and their ``eval/normalized_score``: an offline policy that is not
    return-conditioned (TD3+BC)."""

    def evaluate(agent, env: gym.Env, start_seeds: list[int]):
        returns = run_episodes(agent, env, start_seeds)
        score = normalize(float(returns.mean()))
        return returns, {} if score is None else {"eval/normalized_score": score}

    return evaluate


def offline_evaluation(agent: Agent, normalize: Normalize) -> Evaluation:
    """How an offline agent is evaluated: per target return if it is return-conditioned (DT),
    else greedily; both with normalized scores."""
    if agent.return_conditioned:
        return per_target_return(normalize)
    return scored_greedy(normalize)


def with_normalized_score(normalize: Normalize) -> Callable[[dict], dict]:
    """A run summary plus ``final/normalized_score`` where there are reference returns."""

    def summarize(summary: dict[str, float]) -> dict[str, float]:
        score = normalize(summary.get("final/return_mean", float("nan")))
        return summary if score is None else summary | {"final/normalized_score": score}

    return summarize
