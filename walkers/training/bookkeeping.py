"""Per-run bookkeeping that every training loop shares, and how a run is evaluated.

A loop only acts, steps, observes and updates (:mod:`walkers.training.loops`); after each step it
hands the :class:`RunBook` the step's losses, and :meth:`RunBook.after_step` does what is due
there, top to bottom: the metrics log and the divergence check (every ``log_every`` steps), the
evaluation and a sweep's pruner (every ``eval_every`` and at the last), a video (every
``video_every``), a checkpoint (every ``checkpoint_every``). The book also holds the run's
progress, its checkpoints (``last.pt``, ``best.pt``, the local resume copy, each a
:class:`~walkers.training.run.Checkpoint`), the training env's first reset, the episode
log, the CPU-time count and the ``final/*`` summary. A resumed run's book starts from its last
checkpoint (``start``). A population has one book per member.

An evaluation is greedy episodes from the run's start states (:func:`greedy_evaluation`), or, for
a return-conditioned agent (the Decision Transformer), greedy episodes per target return. The
greedy episodes themselves (:func:`run_episodes`, a population's together
:func:`run_population_episodes`, with frames :func:`record_episodes`) are played here for the
trainer, ``walkers.evaluate`` and ``walkers.collect`` alike.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch

from walkers.agents.base import Agent
from walkers.agents.common.health import SKIPPED_IN_A_ROW
from walkers.metrics import normalized_score, run_summary
from walkers.seeding import (
    env_rng_state,
    eval_start_seeds,
    restore_env_rng,
    restore_torch_rng,
    torch_rng_state,
    training_env_seed,
)
from walkers.training.provenance import DIVERGED_TAG
from walkers.training.run import Axis, Checkpoint, TrainingRun
from walkers.training.settings import RunSettings
from walkers.training.video import write_gif

log = logging.getLogger("walkers")

CPU_HOURS = "perf/cpu_hours"
#: Frames kept in a training video's gif (a glance, not a film).
TRAINING_GIF_FRAMES = 500


class TrainingDiverged(RuntimeError):
    """Every update for ``divergence_patience`` updates in a row had a NaN/inf loss."""


@dataclass
class Progress:
    """Resumable loop state."""

    step: int = 0  # env steps (offline: gradient steps) taken
    episodes: int = 0  # training episodes finished
    eval_steps: list[int] = field(default_factory=list)
    eval_means: list[float] = field(default_factory=list)
    best_eval: float = -math.inf
    #: process CPU time spent training the run, over all its sessions (a population member: its
    #: share of the process); logged as ``perf/cpu_hours`` and ``final/cpu_hours``
    cpu_seconds: float = 0.0


class RunBook:
    """The bookkeeping of one run (see the module docstring). ``run`` is what the run is: its
    MLflow run and folder, its config (whose settings say the budget, the schedules of
    evaluations, checkpoints, logs and videos, the seed and the divergence patience, and whose
    env's threshold counts ``final/steps_to_threshold``) and what its steps count. ``env`` is the
    training env, a population member's the vector env of all members', its env ``env_member``;
    ``evaluation`` plays the evaluation (greedy episodes unless told), ``summarize`` adds to the
    ``final/*`` summary; ``on_evaluation`` is a sweep trial's pruner, ``(step, eval mean) ->
    stop?``; ``start`` the checkpoint a continued run goes on from (:meth:`continue_from`)."""

    def __init__(
        self,
        agent: Agent,
        run: TrainingRun,
        env: gym.Env | None,
        eval_env: gym.Env,
        video_env: gym.Env | None = None,
        env_member: int | None = None,
        evaluation: Evaluation | None = None,
        summarize: Callable[[dict[str, float]], dict[str, float]] | None = None,
        on_evaluation: Callable[[int, float], bool] | None = None,
        start: Checkpoint | None = None,
    ):
        self.agent, self.run = agent, run
        self.env, self.eval_env, self.video_env, self.env_member = (
            env,
            eval_env,
            video_env,
            env_member,
        )
        self.settings = settings = RunSettings.of(run.config)
        self.evaluation = evaluation or greedy_evaluation
        self.on_evaluation = on_evaluation
        self.summarize = summarize or (lambda summary: summary)  # extra final/* metrics
        # the steps after_step may have work at are multiples of these (or the last)
        periods = (settings.log_every, settings.eval_every, settings.checkpoint_every)
        self._periods = sorted(
            {*periods, *([settings.video_every] if settings.video_every else [])}
        )
        self.stopped_early = False
        self.last_checkpoint_step: int | None = None
        self.progress = Progress()
        # a resumed run's training-env RNG, until its first reset
        self.pending_env_rng: dict | None = None
        self.eval_start_seeds = eval_start_seeds(settings.seed, settings.eval_episodes)
        if start is not None:
            self.continue_from(start)
        self.start_clock(time.perf_counter())

    @property
    def axis(self) -> Axis:
        return self.run.axis

    # --- checkpoints --------------------------------------------------------------------------
    def save_checkpoint(self, name: str = "last.pt") -> None:
        """Write ``name`` and upload it; keep ``last.pt`` whole as the run's local resume copy
        (:meth:`continue_from` goes on from it).

        The uploaded ``last.pt`` holds the replay buffer only with ``save_buffer=true`` (it is
        large); the local resume copy always does, so a resume on this machine is exact.
        """
        last, with_buffer = name == "last.pt", self.settings.save_buffer
        self.cpu_hours()  # counted up to now, so a resume goes on from here
        checkpoint = Checkpoint(
            trainer=dataclasses.asdict(self.progress),
            agent=self.agent.state_dict(with_buffer=last and with_buffer),
            config=self.run.config,
            env_rng=env_rng_state(self.env, self.env_member) if self.env is not None else None,
            **torch_rng_state(),
        )
        whole = None
        if last:
            whole = (
                checkpoint
                if with_buffer
                else checkpoint.with_agent(self.agent.state_dict(with_buffer=True))
            )
        self.run.save_checkpoint(name, checkpoint, resume_copy=whole)

    def continue_from(self, start: Checkpoint) -> None:
        """Go on with the run from ``start``, a checkpoint :meth:`save_checkpoint` wrote: the
        agent, the loop's progress, torch's RNGs, the training env's RNG (taken at the first
        reset), and the agent's resume notes as run tags."""
        self.agent.load_state_dict(start.agent)
        self.progress = Progress(**start.progress)
        self.last_checkpoint_step = self.progress.step
        restore_torch_rng({"torch_rng": start.torch_rng, "cuda_rng": start.cuda_rng})
        self.pending_env_rng = start.env_rng
        mark = self.run.logged_through
        if mark is not None and mark > self.progress.step:
            log.warning(
                "run %s logged metrics up to step %d before it stopped; it resumes from its "
                "checkpoint at step %d and logs from step %d on (no step is logged twice)",
                self.run.run_id,
                mark,
                self.progress.step,
                mark + 1,
            )
        if notes := self.agent.resume_notes():  # e.g. a replay buffer that had to be refilled
            if refill := notes.get("walkers.buffer_refill"):
                log.warning(
                    "run %s resumed without the replay buffer's transitions: refilling them, "
                    "%s, before updating again",
                    self.run.run_id,
                    refill,
                )
            self.run.set_tags(notes)

    def checkpoint_and_flush(self) -> None:
        self.save_checkpoint("last.pt")
        self.last_checkpoint_step = self.progress.step
        self.run.flush()

    # --- the training env ---------------------------------------------------------------------
    def first_reset(self):
        """The loop's first reset: seeded from the run's seed in a fresh run; in a resumed one the
        env's RNG continues from the checkpoint (an interrupted episode cannot be continued, so
        a new one starts where the uninterrupted run's next episode would have)."""
        seed = self.first_reset_seed()
        return self.env.reset() if seed is None else self.env.reset(seed=seed)

    def first_reset_seed(self) -> int | None:
        """The seed of this session's first reset of the training env: the run's own in a fresh
        run; None in a resumed run, whose env RNG is restored from its checkpoint here (for a
        loop that resets the env itself, e.g. SB3's)."""
        if self.pending_env_rng is None:
            return training_env_seed(self.settings.seed)
        restore_env_rng(self.env, self.pending_env_rng, self.env_member)
        self.pending_env_rng = None
        return None

    def record_episode(self, episode_return: float, episode_length: int) -> None:
        """A training episode ended at the current step: count it, log its true return (the
        env's own, recorded before any reward shaping: ``info["episode"]``)."""
        p = self.progress
        p.episodes += 1
        self.run.log_metrics(
            {"train/episode_return": episode_return, "train/episode_length": episode_length},
            p.step,
        )

    # --- after every step ---------------------------------------------------------------------
    def start_clock(self, now: float, cpu_share: float = 1.0) -> None:
        """Throughput is measured from ``now`` (a ``time.perf_counter()``) at the current step,
        CPU time from here on, ``cpu_share`` of the process's (1/K for K members of a
        population)."""
        self._cpu_share, self._cpu_mark = cpu_share, time.process_time()
        self._logged_at = (self.progress.step, now)  # the metrics log's throughput since then

    def cpu_hours(self) -> float:
        """The run's CPU-hours so far: its checkpointed total plus this process's CPU time
        (all its threads: torch's, the evaluation's) since the last count, times the share."""
        now = time.process_time()
        self.progress.cpu_seconds += (now - self._cpu_mark) * self._cpu_share
        self._cpu_mark = now
        return self.progress.cpu_seconds / 3600

    def due(self) -> bool:
        """Whether :meth:`after_step` may have work at the current step (a step of most runs has
        none: then it is a few integer checks)."""
        step = self.progress.step
        return step == self.settings.total_steps or any(step % n == 0 for n in self._periods)

    def after_step(self, losses: Mapping[str, torch.Tensor | float]) -> bool:
        """What is due after the current step, in this order (``losses``: the step's scalars,
        tensors or floats); True when a sweep's pruner stops the run (nothing after it runs)."""
        if not self.due():
            return False
        p, s = self.progress, self.settings
        step, last = p.step, p.step == s.total_steps
        if step % s.log_every == 0:
            self.log_metrics(losses)
            self.check_divergence(losses)
        if step % s.eval_every == 0 or last:
            self.evaluate()
            if self.on_evaluation is not None and not last:
                if self.on_evaluation(step, p.eval_means[-1]):
                    self.stopped_early = True  # a finished run is never "stopped early"
                    return True
        if s.video_every and step % s.video_every == 0:
            self.record_video()
        if step % s.checkpoint_every == 0 and not last:  # the last one is finish's
            self.checkpoint_and_flush()
        return False

    def log_metrics(self, losses: Mapping[str, torch.Tensor | float]) -> None:
        """The step's losses, the throughput since the last log, the CPU-hours so far."""
        step, now = self.progress.step, time.perf_counter()
        since, then = self._logged_at
        self._logged_at = (step, now)
        scalars = {key: float(value) for key, value in losses.items()}  # tensors or floats
        rate = (step - since) / (now - then)
        self.run.log_metrics(
            {self.axis.rate_metric: rate, CPU_HOURS: self.cpu_hours()} | scalars, step
        )

    def check_divergence(self, losses: Mapping[str, torch.Tensor | float]) -> None:
        """End the run FAILED (tagged with the step, its last good checkpoint kept) when its
        last ``divergence_patience`` updates all had a NaN/inf loss or gradient, each skipped by
        the NaN guard (:mod:`walkers.agents.common.health`)."""
        if SKIPPED_IN_A_ROW not in losses:
            return
        in_a_row, step = float(losses[SKIPPED_IN_A_ROW]), self.progress.step
        if in_a_row < self.settings.divergence_patience:
            return
        named = ", ".join(f"{k}={float(v)}" for k, v in losses.items() if k.startswith("loss/"))
        kept = (
            f"checkpoints/last.pt (step {self.last_checkpoint_step}) is the last good one"
            if self.last_checkpoint_step is not None
            else "no checkpoint had been written yet"
        )
        self.run.set_tags({DIVERGED_TAG: str(step)})
        raise TrainingDiverged(
            f"training diverged at step {step}: the last {int(in_a_row)} updates all had a "
            f"NaN/inf loss or gradient ({named}) and were skipped; {kept}"
        )

    def evaluate(self) -> None:
        """The run's evaluation (greedy episodes, or an offline run's normalized score):
        ``eval/*`` logged, ``best.pt`` on a new best, and a flush, so the curves move in the
        UI."""
        p = self.progress
        returns, extra = self.evaluation(self.agent, self.eval_env, self.eval_start_seeds)
        mean = float(returns.mean())
        p.eval_steps.append(p.step)
        p.eval_means.append(mean)
        metrics = {"eval/return_mean": mean, "eval/return_std": float(returns.std())}
        self.run.log_metrics(metrics | extra, p.step)
        if mean > p.best_eval:
            p.best_eval = mean
            self.save_checkpoint("best.pt")
        self.run.flush()

    def record_video(self) -> None:
        """A gif of one greedy episode, from the first evaluation start state, to ``videos/``."""
        _, frames, fps = record_episodes(self.agent, self.video_env, self.eval_start_seeds[:1])
        path = self.run.folder.video(self.progress.step)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_gif(frames[:TRAINING_GIF_FRAMES], path, fps)
        self.run.upload(path, "videos")

    # --- the end ------------------------------------------------------------------------------
    def finish(self, rate: float | None, extra: dict[str, float] | None = None) -> dict:
        """Log the ``final/*`` summary (with ``rate`` and ``extra``), write last.pt, flush."""
        p = self.progress
        threshold = self.run.config["env"]["threshold"]
        summary = self.summarize(run_summary(p.eval_steps, p.eval_means, threshold))
        summary |= (extra or {}) | {"final/cpu_hours": self.cpu_hours()}
        if rate is not None:
            summary[self.axis.rate_metric] = rate
        self.run.log_metrics(summary, p.step)
        self.checkpoint_and_flush()
        return summary


# --- how a run is evaluated -------------------------------------------------------------------
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
