"""Per-run bookkeeping that every training loop shares.

A loop only acts, steps, observes and updates (:mod:`walkers.training.loops`); after each step it
hands the :class:`RunBook` the step's losses, and :meth:`RunBook.after_step` does what is due
there, top to bottom: the metrics log and the divergence check (every ``log_every`` steps), the
evaluation and a sweep's pruner (every ``eval_every`` and at the last), a video (every
``video_every``), a checkpoint (every ``checkpoint_every``). The book also holds the run's
progress, its checkpoints (``last.pt``, ``best.pt``, the local resume copy, each a
:class:`~walkers.training.checkpoints.Checkpoint`), the training env's first reset, the episode
log, the CPU-time count and the ``final/*`` summary. A resumed run's book starts from its last
checkpoint (``start``). A population has one book per member.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping
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
from walkers.training.checkpoints import Checkpoint
from walkers.training.evaluation import Evaluation, greedy_evaluation, record_episodes
from walkers.training.provenance import DIVERGED_TAG
from walkers.training.run import Axis, TrainingRun
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
        evaluation: Evaluation = greedy_evaluation,
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
        self.evaluation, self.on_evaluation = evaluation, on_evaluation
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
