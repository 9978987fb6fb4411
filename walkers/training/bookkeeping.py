"""Per-run bookkeeping that every training loop shares.

A loop only acts, steps, observes and updates (:mod:`walkers.training.loops`); after each step it
hands the :class:`RunBook` the step's losses, and the book does the rest for its run: progress
counters, metric logging, evaluations (``eval/*``, ``best.pt``), videos, checkpoints
(``last.pt`` and the local resume copy), the divergence check, the pruning callback, and the
``final/*`` summary. A population has one book per member.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import gymnasium as gym
import torch

from walkers.agents.base import Agent
from walkers.agents.common.health import SKIPPED_IN_A_ROW
from walkers.metrics import run_summary
from walkers.seeding import (
    env_rng_state,
    eval_start_seeds,
    restore_env_rng,
    restore_torch_rng,
    torch_rng_state,
    training_env_seed,
)
from walkers.training.evaluation import Evaluation, greedy_evaluation
from walkers.training.greedy_episodes import record_episodes
from walkers.training.provenance import DIVERGED_TAG
from walkers.training.run import ENV_STEP_AXIS, Axis, TrainingRun
from walkers.training.settings import RunSettings
from walkers.training.video import write_gif

log = logging.getLogger("walkers")

CPU_HOURS = "perf/cpu_hours"

#: Frames kept in the gif logged every ``video_every`` steps (a glance, not a film).
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
    """The bookkeeping of one run (see the module docstring): its ``settings`` say the budget,
    the schedules of evaluations, checkpoints, logs and videos, the seed and the divergence
    patience; ``threshold`` is the env's return for ``final/steps_to_threshold``."""

    def __init__(
        self,
        agent: Agent,
        env: gym.Env | None,
        eval_env: gym.Env,
        run: TrainingRun,
        settings: RunSettings,
        threshold: float,
        checkpoint_extra: dict | None = None,
        video_env: gym.Env | None = None,
        on_evaluation: Callable[[int, float], bool] | None = None,
        evaluation: Evaluation = greedy_evaluation,
        axis: Axis = ENV_STEP_AXIS,
        summarize: Callable[[dict[str, float]], dict[str, float]] | None = None,
    ):
        self.agent, self.env, self.eval_env, self.video_env = agent, env, eval_env, video_env
        self.run, self.settings, self.threshold, self.axis = run, settings, threshold, axis
        self.checkpoint_extra = checkpoint_extra or {}  # e.g. the composed config
        # called with (step, eval mean) after each evaluation; True stops training (a pruned trial)
        self.on_evaluation = on_evaluation
        self.evaluation = evaluation
        self.summarize = summarize or (lambda summary: summary)  # extra final/* metrics
        self.stopped_early = False
        self.last_checkpoint_step: int | None = None
        self.progress = Progress()
        self._env_rng: dict | None = None  # a resumed run's training-env RNG, until its reset
        self.eval_start_seeds = eval_start_seeds(settings.seed, settings.eval_episodes)
        self.start_clock(time.perf_counter())

    # --- checkpoints --------------------------------------------------------------------------
    def restore(self, state: dict) -> None:
        """Continue from a checkpoint written by :meth:`save_checkpoint`."""
        self.agent.load_state_dict(state["agent"])
        # a checkpoint from before runs counted their CPU time: the total is unknown, not 0
        self.progress = Progress(**{"cpu_seconds": math.nan} | state["trainer"])
        self.last_checkpoint_step = self.progress.step
        restore_torch_rng(state)
        self._env_rng = state.get("env_rng")
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

    def save_checkpoint(self, name: str = "last.pt") -> None:
        """Write ``name`` and upload it; keep ``last.pt`` whole as the run's local resume copy.

        The uploaded ``last.pt`` holds the replay buffer only with ``save_buffer=true`` (it is
        large); the local resume copy always does, so a resume on this machine is exact.
        """
        last = name == "last.pt"
        self.cpu_hours()  # counted up to now, so a resume goes on from here
        state = {
            "trainer": dataclasses.asdict(self.progress),
            **torch_rng_state(),
            "env_rng": env_rng_state(self.env) if self.env is not None else None,
            **self.checkpoint_extra,
        }
        whole = None
        if last and not self.settings.save_buffer:
            whole = state | {"agent": self.agent.state_dict(with_buffer=True)}
        state["agent"] = self.agent.state_dict(with_buffer=last and self.settings.save_buffer)
        if last and self.settings.save_buffer:
            whole = state
        self.run.save_checkpoint(name, state, resume_state=whole)

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
        if self._env_rng is None:
            return training_env_seed(self.settings.seed)
        restore_env_rng(self.env, self._env_rng)
        self._env_rng = None
        return None

    def record_episode(self, info: dict) -> None:
        """A training episode ended at the current step: count it, log its true return."""
        p = self.progress
        p.episodes += 1
        episode = info["episode"]  # recorded before any reward shaping
        self.run.log_metrics(
            {"train/episode_return": episode["r"], "train/episode_length": episode["l"]}, p.step
        )

    # --- after every step ---------------------------------------------------------------------
    def start_clock(self, now: float, cpu_share: float = 1.0) -> None:
        """Throughput is measured from ``now`` (a ``time.perf_counter()``) at the current step,
        CPU time from here on, ``cpu_share`` of the process's (1/K for K members of a
        population)."""
        self._log_step, self._log_time = self.progress.step, now
        self._cpu_share, self._cpu_mark = cpu_share, time.process_time()

    def cpu_hours(self) -> float:
        """The run's CPU-hours so far: its checkpointed total plus this process's CPU time
        (all its threads: torch's, the evaluation's) since the last count, times the share."""
        now = time.process_time()
        self.progress.cpu_seconds += (now - self._cpu_mark) * self._cpu_share
        self._cpu_mark = now
        return self.progress.cpu_seconds / 3600

    def after_step(self, losses: dict[str, torch.Tensor]) -> bool:
        """Log, evaluate, film, checkpoint when due; True when the run should stop early."""
        s, p = self.settings, self.progress
        if p.step % s.log_every == 0:
            now = time.perf_counter()
            rate = (p.step - self._log_step) / (now - self._log_time)
            self._log_step, self._log_time = p.step, now
            scalars = {k: v.item() for k, v in losses.items()}
            metrics = {self.axis.rate_metric: rate, CPU_HOURS: self.cpu_hours(), **scalars}
            self.run.log_metrics(metrics, p.step)
            self._check_divergence(scalars)
        if p.step % s.eval_every == 0 or p.step == s.total_steps:
            mean = self.evaluate()
            self.run.flush()  # the curves move in the UI at every evaluation
            if (
                self.on_evaluation is not None
                and p.step < s.total_steps  # a finished run is never "stopped early"
                and self.on_evaluation(p.step, mean)
            ):
                self.stopped_early = True
                return True
        if s.video_every and p.step % s.video_every == 0:
            self.record_video()
        if p.step % s.checkpoint_every == 0 and p.step < s.total_steps:  # the end: in finish()
            self.checkpoint_and_flush()
        return False

    def _check_divergence(self, scalars: dict[str, float]) -> None:
        in_a_row = scalars.get(SKIPPED_IN_A_ROW, 0.0)
        if in_a_row >= self.settings.divergence_patience:
            losses = ", ".join(f"{k}={v}" for k, v in scalars.items() if k.startswith("loss/"))
            kept = (
                f"checkpoints/last.pt (step {self.last_checkpoint_step}) is the last good one"
                if self.last_checkpoint_step is not None
                else "no checkpoint had been written yet"
            )
            self.run.set_tags({DIVERGED_TAG: str(self.progress.step)})
            raise TrainingDiverged(
                f"training diverged at step {self.progress.step}: the last {int(in_a_row)} "
                f"updates all had a NaN/inf loss or gradient ({losses}) and were skipped; {kept}"
            )

    # --- evaluation ---------------------------------------------------------------------------
    def evaluate(self) -> float:
        """Run the evaluation; log ``eval/*``, keep ``best.pt``; returns the mean return."""
        returns, extra = self.evaluation(self.agent, self.eval_env, self.eval_start_seeds)
        p = self.progress
        mean = float(returns.mean())
        p.eval_steps.append(p.step)
        p.eval_means.append(mean)
        metrics = {"eval/return_mean": mean, "eval/return_std": float(returns.std())}
        self.run.log_metrics(metrics | extra, p.step)
        if mean > p.best_eval:
            p.best_eval = mean
            self.save_checkpoint("best.pt")
        return mean

    def record_video(self) -> None:
        """Log a gif of one greedy episode (from the first eval start state) to ``videos/``."""
        _, frames, fps = record_episodes(self.agent, self.video_env, self.eval_start_seeds[:1])
        path = self.run.folder.video(self.progress.step)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_gif(frames[:TRAINING_GIF_FRAMES], path, fps)
        self.run.upload(path, "videos")

    # --- the end ------------------------------------------------------------------------------
    def finish(self, rate: float | None, extra: dict[str, float] | None = None) -> dict:
        """Log the ``final/*`` summary (with ``rate`` and ``extra``), write last.pt, flush."""
        p = self.progress
        summary = self.summarize(run_summary(p.eval_steps, p.eval_means, self.threshold))
        summary |= (extra or {}) | {"final/cpu_hours": self.cpu_hours()}
        if rate is not None:
            summary[self.axis.rate_metric] = rate
        self.run.log_metrics(summary, p.step)
        self.checkpoint_and_flush()
        return summary
