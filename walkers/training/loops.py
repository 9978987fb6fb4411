"""The training loops: they act, step, observe and update; their runs' books do the rest.

    online:      act -> env step -> observe -> update -> book.after_step
    vectorized:  act on N envs as one batch -> step all -> observe all -> update ->
                 book.after_step once per env, in env order (PPO with num_envs > 1)
    offline:     update (a gradient step on the dataset) -> book.after_step
    population:  act all -> step the K envs as one vector env -> store all -> one update ->
                 the books, once for all K when anything is due (:class:`Lockstep`)
    sb3:         Stable-Baselines3's own learn() loop; its callback -> book.after_step

Off-policy agents learn every step after their warm-up, on-policy ones when their batch is
complete (REINFORCE: episodes; PPO: a rollout of steps): the agent decides inside ``update()``,
the loop is the same. Every loop reads top to bottom inside :func:`progress_shown` (a progress
bar; on Ctrl-C, or SIGTERM turned into one, a last checkpoint of every run before the interrupt
propagates) and ends with :func:`finish_runs` (each run's summary, with its throughput over the
session).

A stop lands between steps, never inside one: each step of walkers' own loops (act, env step,
observe, update, and its logging, evaluation and checkpoint when due) runs shielded
(:func:`walkers.interrupts.shielded`) and the signal is raised when the step is over; SB3's
``learn`` runs shielded whole, and its callback ends it at the next env step. So the last
checkpoint holds whole updates at a consistent count, and an offline run resumed from it logs
what the uninterrupted run logs, bit for bit (a stop inside TD3's update once left its critic
stepped and the step uncounted: the resume stepped that critic twice).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

from walkers.agents.base import Agent, Transition
from walkers.agents.common.actor_critic import ActorCritic
from walkers.agents.sb3.twin import SB3Twin
from walkers.interrupts import shielded, stop_noted, stops_between_steps
from walkers.training.bookkeeping import RunBook


def train_online(agent: Agent, env: gym.Env, book: RunBook) -> dict[str, float]:
    """Until ``total_steps`` env steps (or a pruner stops the run); returns the summary."""
    p = book.progress
    with progress_shown([book]) as bar:
        obs, _ = book.first_reset()
        losses: dict[str, torch.Tensor] = {}
        while p.step < book.settings.total_steps:
            with shielded():
                obs, episode = online_step(agent, env, obs, losses)
                p.step += 1
                if episode is not None:
                    book.record_episode(*episode)
                stop = _after_step(book, losses, bar)
            if stop:
                break
    return finish_runs([book], bar)[0]


def online_step(agent: Agent, env: gym.Env, obs, losses: dict) -> tuple[np.ndarray, tuple | None]:
    """One env step of a single run: act, step, observe, update (its losses into ``losses``);
    the next observation (a new episode's first where one ended) and the ended episode's
    ``(return, length)``, or None."""
    action = agent.act(obs, explore=True)
    next_obs, reward, terminated, truncated, info = env.step(action)
    agent.observe(Transition(obs, action, float(reward), next_obs, terminated, truncated))
    losses.update(agent.update())
    if not (terminated or truncated):
        return next_obs, None
    episode = info["episode"]
    return env.reset()[0], (episode["r"], episode["l"])


def train_vectorized(
    agent: Agent, envs: gym.vector.SyncVectorEnv, book: RunBook
) -> dict[str, float]:
    """Until ``total_steps`` env steps summed over the ``num_envs`` envs (a multiple of it, as
    ``checkpoint_every`` is: walkers.training.settings.validate), which finish their episodes in the
    step (``AutoresetMode.SAME_STEP``); returns the summary."""
    p, n = book.progress, envs.num_envs
    with progress_shown([book]) as bar:
        obs, _ = book.first_reset()  # env i from the run's seed + i
        losses: dict[str, torch.Tensor] = {}
        stop = False
        while not stop and p.step < book.settings.total_steps:
            with shielded():
                step = vectorized_step(agent, envs, obs, losses)
                obs = step.next_obs
                for i in range(n):
                    p.step += 1
                    if i in step.ended:
                        book.record_episode(*step.episode_statistics(i))
                    stop = _after_step(book, losses, bar)
                    if stop:
                        break
    return finish_runs([book], bar)[0]


def vectorized_step(agent: Agent, envs: gym.vector.VectorEnv, obs, losses: dict) -> VectorStep:
    """One step of every env of a run on several envs: act on them as one batch, step, observe,
    update (its losses into ``losses``)."""
    step = step_vector_env(envs, obs, agent.act(obs, explore=True))
    agent.observe_batch(step.transitions())
    losses.update(agent.update())
    return step


class VectorStep(NamedTuple):
    """One step of every env of a vector env (:func:`step_vector_env`), as ``(N, ...)`` arrays."""

    obs: np.ndarray  # what each env was shown before the step
    actions: np.ndarray
    rewards: np.ndarray
    own_next_obs: np.ndarray  # each env's own next observation: a finished episode's last one
    terminated: np.ndarray
    truncated: np.ndarray
    next_obs: np.ndarray  # what each env shows now: a finished episode's env already reset
    info: dict
    ended: np.ndarray  # the indices of the envs whose episode ended in the step

    @property
    def episode_over(self) -> np.ndarray:
        return self.terminated | self.truncated

    def transitions(self) -> list[Transition]:
        """Each env's step as a :class:`Transition` (an agent that observes them one by one)."""
        return [
            Transition(
                self.obs[i],
                self.actions[i],
                float(self.rewards[i]),
                self.own_next_obs[i],
                bool(self.terminated[i]),
                bool(self.truncated[i]),
            )  # fmt: skip
            for i in range(len(self.rewards))
        ]

    def episode_statistics(self, i: int) -> tuple[float, int]:
        """The true return and length of env ``i``'s episode, which ended in the step."""
        episode = self.info["final_info"]["episode"]
        return float(episode["r"][i]), int(episode["l"][i])


def step_vector_env(envs: gym.vector.VectorEnv, obs: np.ndarray, actions) -> VectorStep:
    """Step every env of ``envs`` (finishing episodes in the step:
    :func:`walkers.training.envs.make_vector_env`) from observations ``obs`` with ``actions``."""
    next_obs, rewards, terminated, truncated, info = envs.step(actions)
    ended = np.flatnonzero(terminated | truncated)
    own_next_obs = next_obs
    if len(ended):  # a finished episode's own last observation, not the next episode's first
        own_next_obs = next_obs.copy()
        for i in ended:
            own_next_obs[i] = info["final_obs"][i]
    return VectorStep(
        obs, actions, rewards, own_next_obs, terminated, truncated, next_obs, info, ended
    )


def train_offline(agent: Agent, book: RunBook) -> dict[str, float]:
    """Until ``total_steps`` gradient steps on the agent's dataset; returns the summary."""
    p = book.progress
    with progress_shown([book]) as bar:
        while p.step < book.settings.total_steps:
            with shielded():
                losses = agent.update()
                p.step += 1
                stop = _after_step(book, losses, bar)
            if stop:
                break
    return finish_runs([book], bar)[0]


def train_population(
    agent: ActorCritic, envs: gym.vector.VectorEnv, books: Sequence[RunBook]
) -> list[dict[str, float]]:
    """K members in one agent, their K envs one vector env, one book each, in lockstep; one
    summary each (with ``perf/population_sps``, the aggregate throughput)."""
    first = books[0]  # the members share the step, the budget and the schedules
    with progress_shown(books) as bar:
        # each member's env seeded as a single run of its seed is (or its RNG restored)
        obs, _ = envs.reset(seed=[book.first_reset_seed() for book in books])
        lockstep = Lockstep(agent, envs, obs)
        while first.progress.step < first.settings.total_steps:
            with shielded():
                step, losses = lockstep.step()
                _population_books(books, step, losses, bar)
    return finish_runs(books, bar, aggregate="perf/population_sps")


class Lockstep:
    """The population's step, arrays end to end: the K members act as one batch, their K envs
    step as one vector env (finished episodes reset in the step), the K transitions go into the
    replay buffer as ``(K, ...)`` arrays, and one update trains every member. The trainer and
    ``benchmarks/bench_throughput.py`` both step through it."""

    def __init__(self, agent: ActorCritic, envs: gym.vector.VectorEnv, obs: np.ndarray):
        self.agent, self.envs, self.obs = agent, envs, obs
        self.latest: dict[str, torch.Tensor] = {}  # each metric's last value, ``(K,)``

    def step(self) -> tuple[VectorStep, dict[str, torch.Tensor]]:
        """One lockstep step: the envs' step and the latest value of every update metric."""
        actions = self.agent.act_population(self.obs, explore=True)
        step = step_vector_env(self.envs, self.obs, actions)
        self.agent.store_steps(
            step.obs,
            step.actions,
            step.rewards,
            step.own_next_obs,
            step.terminated,
            step.episode_over,
        )
        self.obs = step.next_obs
        self.latest.update(self.agent.update())
        return step, self.latest


def _population_books(books: Sequence[RunBook], step: VectorStep, losses, bar: tqdm) -> None:
    """The K books after a lockstep step: the ended episodes recorded, each step counted, and
    only when something is due at this step (the members share the schedules), each book's
    after_step, its losses read from the device in one transfer when they are logged."""
    for book in books:
        book.progress.step += 1
    for i in step.ended:
        books[i].record_episode(*step.episode_statistics(i))
    first = books[0]
    if first.due():
        logging = first.progress.step % first.settings.log_every == 0
        per_member = member_scalars(losses, len(books)) if logging else [{}] * len(books)
        for book, scalars in zip(books, per_member, strict=True):
            book.after_step(scalars)
    _progress_bar(first, bar)


def member_scalars(losses: dict[str, torch.Tensor], k: int) -> list[dict[str, float]]:
    """Each member's value of every ``(K,)`` metric, as floats: one device-to-host transfer."""
    if not losses:
        return [{} for _ in range(k)]
    names = list(losses)
    stacked = torch.stack([losses[name].detach().float().reshape(k) for name in names])
    columns = stacked.cpu().tolist()
    return [dict(zip(names, values, strict=True)) for values in zip(*columns, strict=True)]


def train_sb3(agent: SB3Twin, book: RunBook) -> dict[str, float]:
    """``impl=sb3``: SB3's ``learn`` runs its own collection and updates; after every env step
    its callback hands the book SB3's latest losses (under walkers' names), so evaluations,
    checkpoints, pruning and ``final/*`` are a walkers run's. Returns the summary.

    SB3 calls back after the env step and before it stores and learns from that step: an
    evaluation or checkpoint at step s sees the agent of s - 1 updates (at the end of the run,
    all of them). A resume starts a new episode, as a walkers resume does.
    """
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    p, s = book.progress, book.settings
    on_policy = isinstance(agent.model, OnPolicyAlgorithm)

    class BookKeeping(BaseCallback):
        def __init__(self, bar: tqdm):
            super().__init__()
            self.bar = bar

        def _on_step(self) -> bool:
            p.step = self.num_timesteps
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
                if done:
                    book.record_episode(info["episode"]["r"], info["episode"]["l"])
            losses = agent.latest_losses() if p.step % s.log_every == 0 else {}
            stop = _after_step(book, losses, self.bar) or stop_noted()
            # SB3's PPO would complete its rollout past the budget; its off-policy loop stores
            # and learns from the last step, then stops by itself
            return not stop and not (on_policy and p.step >= s.total_steps)

    with progress_shown([book]) as bar:
        if (seed := book.first_reset_seed()) is not None:
            agent.vec_env.seed(seed)  # SB3 resets the env itself, with this seed first
        with shielded():  # a stop ends learn() at SB3's next env step, never inside an update
            agent.model.learn(
                s.total_steps - p.step, callback=BookKeeping(bar), reset_num_timesteps=False
            )
    return finish_runs([book], bar)[0]


def _after_step(book: RunBook, losses: dict[str, torch.Tensor], bar: tqdm) -> bool:
    stop = book.after_step(losses)
    _progress_bar(book, bar)
    return stop


def _progress_bar(book: RunBook, bar: tqdm) -> None:
    """After an evaluation the bar shows its return; every 100 steps it moves, with its ETA."""
    step = book.progress.step
    if step % 100 == 0 or step in book.progress.eval_steps[-1:]:
        bar.set_postfix(bar.eta(step) | _latest_evaluation(book), refresh=False)
        bar.update(step - bar.n)


class ProgressBar(tqdm):
    """tqdm with where and when this session started (its throughput's origin) and its own time
    left, each phase at its own rate. An off-policy run's first steps (random actions, no
    updates: ``agent.update_after``, here ``learning_from``) run many times faster than its
    learning phase, so a rate over both (tqdm's own ETA) said minutes for a run of hours. During
    the warm-up the bar says when learning starts; from then on, the time left is the steps left
    at the rate measured since learning started in this session (evaluations included)."""

    def __init__(self, total: int, learning_from: int, initial: int = 0, postfix=None, **kwargs):
        self.total, self.learning_from, self.first_step = total, learning_from, initial
        self.mark: tuple[int, float] | None = None  # this session's first learning step, time
        postfix = self.eta(initial) | (postfix or {})
        super().__init__(total=total, initial=initial, postfix=postfix, **kwargs)
        self.start = time.perf_counter()

    def eta(self, step: int, now: float | None = None) -> dict[str, str]:
        """The bar's ``eta`` field at ``step`` (``now``: a ``time.perf_counter()``)."""
        now = time.perf_counter() if now is None else now
        if step >= self.total:
            return {}
        if step < self.learning_from:
            return {"eta": f"after the warm-up to step {self.learning_from:,}"}
        if self.mark is None:
            self.mark = (step, now)
        start, then = self.mark
        if step - start < 100 or now <= then:
            return {"eta": "measuring the learning phase"}
        rate = (step - start) / (now - then)
        return {"eta": tqdm.format_interval((self.total - step) / rate)}


def _latest_evaluation(book: RunBook) -> dict[str, str]:
    """The bar's field for the run's latest evaluation (a resumed run's: its checkpoint's)."""
    means = book.progress.eval_means
    return {"eval_return": f"{means[-1]:.1f}"} if means else {}


@contextmanager
def progress_shown(books: Sequence[RunBook]) -> Iterator[ProgressBar]:
    """The loop's progress bar, from the books' step on (a resumed run's with its latest
    evaluation's return), their clocks started; on Ctrl-C every run's last checkpoint before the
    interrupt propagates. A Ctrl-C lands between steps, however the training was started
    (:func:`walkers.interrupts.stops_between_steps`), so the book's step and the agent's count
    of what it observed agree in every checkpoint: the book's progress is the run's step count,
    and nothing has to reconcile the two."""
    first = books[0]
    s, p = first.settings, first.progress
    bar = ProgressBar(
        s.total_steps,
        getattr(first.agent, "update_after", 0),
        initial=p.step,
        postfix=_latest_evaluation(first),
        unit=first.axis.unit,
        disable=not s.progress,
        dynamic_ncols=True,
        mininterval=1.0,
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, {rate_fmt}{postfix}]",
    )
    for book in books:
        book.start_clock(bar.start, cpu_share=1 / len(books))
    with stops_between_steps():  # the last checkpoints too: a second Ctrl-C waits for them
        try:
            yield bar
        except KeyboardInterrupt:
            for book in books:
                book.checkpoint_and_flush()
            raise
        finally:  # the bar's last line: the step the run ended at (or its checkpoint holds)
            bar.update(p.step - bar.n)
            bar.close()


def finish_runs(
    books: Sequence[RunBook], bar: ProgressBar, aggregate: str | None = None
) -> list[dict[str, float]]:
    """Each run's ``final/*`` summary, with its throughput over this session (``rate_metric``);
    ``aggregate`` names a metric for the throughput of all the books together (a
    population's)."""
    p = books[0].progress
    if p.step == bar.first_step:  # resumed at its budget: nothing ran, no rate
        return [book.finish(None) for book in books]
    rate = (p.step - bar.first_step) / (time.perf_counter() - bar.start)
    extra = {aggregate: rate * len(books)} if aggregate else {}
    return [book.finish(rate, extra) for book in books]
