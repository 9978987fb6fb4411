"""``population=K``: K seeds of TD3/DDPG trained in one process, each logged as its own run.

    python -m walkers.train algo=td3 env=walker2d population=5 seed=0   # seeds 0..4, 5 runs

The agent holds all members as ensembles (:class:`walkers.agents.actor_critic.ActorCritic` with
``population=K``) and updates them in one batched step; each member has its own env, eval env,
MLflow run, evaluations and checkpoints. A member's run looks exactly like a single run with its
seed (params, tags, metrics, ``best.pt``/``last.pt`` in the single-agent layout), plus the tags
``walkers.population`` (K) and ``walkers.population_member`` (its index): `walkers.evaluate`,
`walkers.collect` and `walkers.compare` treat it as any run; ``resume=<member run>`` continues
that member alone, ``resume=[<run>,<run>,...]`` the members together again (runs of one
configuration at the same step; the end of a population run prints that command). The members
share the loop, so they stop together: Ctrl-C ends every run KILLED, a member whose updates keep
failing (``divergence_patience``) ends every run FAILED.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from tqdm import tqdm

from walkers.agents.actor_critic import ActorCritic
from walkers.agents.base import Transition
from walkers.trainer import Trainer

POPULATION_TAG = "walkers.population"
MEMBER_TAG = "walkers.population_member"


class PopulationTrainer:
    """One loop for K members: act all -> step each env -> observe all -> one update -> per
    member: log, evaluate, checkpoint (each through its own :class:`Trainer`)."""

    def __init__(self, agent: ActorCritic, trainers: list[Trainer]):
        self.agent, self.trainers = agent, trainers

    def run(self) -> list[dict[str, float]]:
        agent, trainers = self.agent, self.trainers
        settings, progress = trainers[0].settings, trainers[0].progress  # shared by all members
        obs = [t.first_reset()[0] for t in trainers]  # each seeded as a single run is
        bar = tqdm(
            total=settings.total_steps,
            initial=progress.step,
            unit="step",
            disable=not settings.progress,
            dynamic_ncols=True,
            mininterval=1.0,
        )
        start_step, start = progress.step, time.perf_counter()
        for t in trainers:
            t.start_clock(start)
        latest: dict[str, torch.Tensor] = {}
        try:
            while progress.step < settings.total_steps:
                actions = agent.act_population(np.stack(obs), explore=True)
                results = [t.env.step(action) for t, action in zip(trainers, actions, strict=True)]
                agent.observe_population(
                    [
                        Transition(obs[i], actions[i], reward, next_obs, terminated, truncated)
                        for i, (next_obs, reward, terminated, truncated, _) in enumerate(results)
                    ]
                )
                for i, (t, result) in enumerate(zip(trainers, results, strict=True)):
                    next_obs, _, terminated, truncated, info = result
                    t.progress.step += 1
                    obs[i] = next_obs
                    if terminated or truncated:
                        t.record_episode(info)
                        obs[i], _ = t.env.reset()
                latest.update(agent.update())
                logging = progress.step % settings.log_every == 0
                for i, t in enumerate(trainers):  # losses are read only when they are logged
                    t.after_step({k: v[i] for k, v in latest.items()} if logging else {}, bar)
        except KeyboardInterrupt:
            for t in trainers:  # members checkpoint at one step, so they resume together
                t.progress.step = agent.steps
                t.checkpoint_and_flush()
            raise
        finally:
            bar.close()
        if progress.step == start_step:  # resumed at its budget: nothing ran, no rate
            return [t.finish(None) for t in trainers]
        sps = (progress.step - start_step) / (time.perf_counter() - start)
        aggregate = {"perf/population_sps": sps * len(trainers)}
        return [t.finish(sps, aggregate) for t in trainers]


