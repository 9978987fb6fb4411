"""The one training loop for every agent.

    act -> step -> observe -> update -> (log) -> (evaluate) -> (checkpoint)

Off-policy agents learn every step after their warm-up, on-policy ones when a batch of episodes
is complete: the agent decides inside ``update()``, the loop is the same. The loop's own state
(:class:`Progress`) goes into every checkpoint so a resumed run continues its counters.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import torch
from tqdm import tqdm

from walkers import checkpoints
from walkers.agents.base import Agent, Transition
from walkers.agents.health import SKIPPED_IN_A_ROW
from walkers.rollout import record_episodes, run_episodes
from walkers.seeding import env_rng_state, eval_start_seeds, first_training_reset, restore_env_rng
from walkers.stats import run_summary
from walkers.tracking import ENV_STEPS, GRADIENT_STEPS, Tracker
from walkers.video import write_gif

#: Where a run keeps its resume checkpoint on the machine that trains it: ``last.pt`` with the
#: replay buffer (exactly what a resume on this machine needs), beside ``checkpoints/``, whose
#: files are uploaded to MLflow (lighter: no buffer unless ``save_buffer=true``).
RESUME_DIR = "resume"


class TrainingDiverged(RuntimeError):
    """Every update for ``divergence_patience`` updates in a row had a NaN/inf loss."""


#: Frames kept in the gif logged every ``video_every`` steps (a glance, not a film).
TRAINING_GIF_FRAMES = 500


@dataclass
class TrainerSettings:
    total_steps: int
    eval_every: int
    eval_episodes: int
    checkpoint_every: int
    log_every: int
    seed: int
    threshold: float
    save_buffer: bool = False
    progress: bool = True
    video_every: int = 0  # env steps between gifs of the greedy policy; 0: never
    divergence_patience: int = 100  # skipped (NaN/inf) updates in a row that end the run FAILED


@dataclass
class Progress:
    """Resumable loop state."""

    step: int = 0  # env steps taken
    episodes: int = 0  # training episodes finished
    eval_steps: list[int] = field(default_factory=list)
    eval_means: list[float] = field(default_factory=list)
    best_eval: float = -math.inf


class Trainer:
    """The online loop: env steps are the x-axis."""

    x_axis = ENV_STEPS  # what `step` counts in every metric of the run
    rate_metric = "perf/sps"  # env steps per second, whole loop
    unit = "step"

    def __init__(
        self,
        agent: Agent,
        env: gym.Env,
        eval_env: gym.Env,
        tracker: Tracker,
        settings: TrainerSettings,
        checkpoint_dir: Path,
        checkpoint_extra: dict | None = None,
        video_env: gym.Env | None = None,
        on_evaluation: Callable[[int, float], bool] | None = None,
    ):
        self.agent, self.env, self.eval_env, self.video_env = agent, env, eval_env, video_env
        self.tracker, self.settings = tracker, settings
        self.checkpoint_dir = Path(checkpoint_dir)
        self.checkpoint_extra = checkpoint_extra or {}  # e.g. the composed config
        # called with (step, eval mean) after each evaluation; True stops training (a pruned trial)
        self.on_evaluation = on_evaluation
        self.stopped_early = False
        self.last_checkpoint_step: int | None = None
        self.progress = Progress()
        self._env_rng: dict | None = None  # a resumed run's training-env RNG, until its reset
        self.eval_start_seeds = eval_start_seeds(settings.seed, settings.eval_episodes)

    # --- checkpoints --------------------------------------------------------------------------
    def restore(self, state: dict) -> None:
        """Continue from a checkpoint written by this class."""
        self.agent.load_state_dict(state["agent"])
        self.progress = Progress(**state["trainer"])
        self.last_checkpoint_step = self.progress.step
        torch.set_rng_state(state["torch_rng"])
        self._env_rng = state.get("env_rng")
        if notes := self.agent.resume_notes():  # e.g. a replay buffer that had to be refilled
            self.tracker.set_tags(notes)

    @property
    def resume_checkpoint(self) -> Path:
        """``last.pt`` with everything a resume needs (the replay buffer included), kept locally."""
        return self.checkpoint_dir.parent / RESUME_DIR / "last.pt"

    def save_checkpoint(self, name: str = "last.pt") -> Path:
        """Write ``name`` and upload it; keep ``last.pt`` whole as :attr:`resume_checkpoint` too.

        The uploaded ``last.pt`` holds the replay buffer only with ``save_buffer=true`` (it is
        large); the local resume copy always does, so a resume on this machine is exact.
        """
        last = name == "last.pt"
        state = {
            "trainer": dataclasses.asdict(self.progress),
            "torch_rng": torch.get_rng_state(),
            "env_rng": env_rng_state(self.env) if self.env is not None else None,
            **self.checkpoint_extra,
        }
        if last and not self.settings.save_buffer:
            whole = state | {"agent": self.agent.state_dict(with_buffer=True)}
            checkpoints.save(whole, self.resume_checkpoint)
        state["agent"] = self.agent.state_dict(with_buffer=last and self.settings.save_buffer)
        path = checkpoints.save(state, self.checkpoint_dir / name)
        if last and self.settings.save_buffer:
            checkpoints.save(state, self.resume_checkpoint)
        self.tracker.log_artifact(path, "checkpoints")
        return path

    def checkpoint_and_flush(self) -> None:
        # Metrics reach MLflow only up to a checkpoint: a resumed run never logs a step twice.
        self.save_checkpoint("last.pt")
        self.last_checkpoint_step = self.progress.step
        self.tracker.flush()

    def _check_divergence(self, scalars: dict[str, float]) -> None:
        in_a_row = scalars.get(SKIPPED_IN_A_ROW, 0.0)
        if in_a_row >= self.settings.divergence_patience:
            losses = ", ".join(f"{k}={v}" for k, v in scalars.items() if k.startswith("loss/"))
            kept = (
                f"checkpoints/last.pt (step {self.last_checkpoint_step}) is the last good one"
                if self.last_checkpoint_step is not None
                else "no checkpoint had been written yet"
            )
            raise TrainingDiverged(
                f"training diverged at step {self.progress.step}: the last {int(in_a_row)} "
                f"updates all had a NaN/inf loss ({losses}) and were skipped; {kept}"
            )

    # --- evaluation ---------------------------------------------------------------------------
    def evaluate(self) -> float:
        """Greedy episodes on the eval env; logs ``eval/*``, keeps best.pt; returns the mean."""
        returns = run_episodes(self.agent, self.eval_env, self.eval_start_seeds)
        return self._record_evaluation(returns)

    def _record_evaluation(self, returns, extra: dict[str, float] | None = None) -> float:
        p = self.progress
        mean = float(returns.mean())
        p.eval_steps.append(p.step)
        p.eval_means.append(mean)
        metrics = {"eval/return_mean": mean, "eval/return_std": float(returns.std())}
        self.tracker.log_metrics(metrics | (extra or {}), p.step)
        if mean > p.best_eval:
            p.best_eval = mean
            self.save_checkpoint("best.pt")
        return mean

    def record_video(self) -> None:
        """Log a gif of one greedy episode (from the first eval start state) to ``videos/``."""
        _, frames, fps = record_episodes(self.agent, self.video_env, self.eval_start_seeds[:1])
        path = self.checkpoint_dir.parent / "videos" / f"step_{self.progress.step:08d}.gif"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_gif(frames[:TRAINING_GIF_FRAMES], path, fps)
        self.tracker.log_artifact(path, "videos")

    # --- the loop -----------------------------------------------------------------------------
    def run(self) -> dict[str, float]:
        """Train until ``total_steps``; returns the ``final/*`` and throughput metrics.

        On KeyboardInterrupt (Ctrl-C, or SIGTERM turned into one) a last checkpoint is saved
        before the exception propagates.
        """
        s, p = self.settings, self.progress
        bar = tqdm(
            total=s.total_steps,
            initial=p.step,
            unit=self.unit,
            disable=not s.progress,
            dynamic_ncols=True,
            mininterval=1.0,
        )
        start_step, start_time = p.step, time.perf_counter()
        self.start_clock(start_time)
        try:
            self._loop(bar)
        except KeyboardInterrupt:
            self.checkpoint_and_flush()
            raise
        finally:
            bar.close()
        elapsed = time.perf_counter() - start_time
        rate = (p.step - start_step) / elapsed if p.step > start_step else None
        return self.finish(rate)

    def start_clock(self, now: float) -> None:
        """Throughput is measured from ``now`` (a ``time.perf_counter()``) at the current step."""
        self._log_step, self._log_time = self.progress.step, now

    def finish(self, rate: float | None, extra: dict[str, float] | None = None) -> dict:
        """Log the ``final/*`` summary (with ``rate`` and ``extra``), write last.pt, flush."""
        summary = self.summary() | (extra or {})
        if rate is not None:
            summary[self.rate_metric] = rate
        self.tracker.log_metrics(summary, self.progress.step)
        self.checkpoint_and_flush()
        return summary

    def summary(self) -> dict[str, float]:
        p = self.progress
        return run_summary(p.eval_steps, p.eval_means, self.settings.threshold)

    def _loop(self, bar: tqdm) -> None:
        """Act, step, observe, update until the budget is spent (or a pruner stops the run)."""
        s, p, agent, env = self.settings, self.progress, self.agent, self.env
        obs, _ = self.first_reset()
        losses: dict[str, torch.Tensor] = {}
        while p.step < s.total_steps:
            action = agent.act(obs, explore=True)
            next_obs, reward, terminated, truncated, info = env.step(action)
            agent.observe(Transition(obs, action, float(reward), next_obs, terminated, truncated))
            losses.update(agent.update())
            p.step += 1
            obs = next_obs
            if terminated or truncated:
                self.record_episode(info)
                obs, _ = env.reset()
            if self.after_step(losses, bar):
                return

    def first_reset(self):
        """The loop's first reset: seeded from the run's seed in a fresh run; in a resumed one the
        env's RNG continues from the checkpoint (an interrupted episode cannot be continued, so
        a new one starts where the uninterrupted run's next episode would have)."""
        if self._env_rng is None:
            return first_training_reset(self.env, self.settings.seed)
        restore_env_rng(self.env, self._env_rng)
        self._env_rng = None
        return self.env.reset()

    def record_episode(self, info: dict) -> None:
        """A training episode ended at the current step: count it, log its true return."""
        p = self.progress
        p.episodes += 1
        episode = info["episode"]  # recorded before any reward shaping
        self.tracker.log_metrics(
            {"train/episode_return": episode["r"], "train/episode_length": episode["l"]}, p.step
        )

    def after_step(self, losses: dict[str, torch.Tensor], bar: tqdm) -> bool:
        """Log, evaluate, film, checkpoint when due; True when the run should stop early."""
        s, p = self.settings, self.progress
        if p.step % s.log_every == 0:
            now = time.perf_counter()
            rate = (p.step - self._log_step) / (now - self._log_time)
            self._log_step, self._log_time = p.step, now
            scalars = {k: v.item() for k, v in losses.items()}
            self.tracker.log_metrics({self.rate_metric: rate, **scalars}, p.step)
            self._check_divergence(scalars)
        if p.step % s.eval_every == 0 or p.step == s.total_steps:
            mean = self.evaluate()
            bar.set_postfix(eval_return=f"{mean:.1f}", refresh=False)
            if (
                self.on_evaluation is not None
                and p.step < s.total_steps  # a finished run is never "stopped early"
                and self.on_evaluation(p.step, mean)
            ):
                self.stopped_early = True
                return True
        if s.video_every and p.step % s.video_every == 0:
            self.record_video()
        if p.step % s.checkpoint_every == 0 and p.step < s.total_steps:  # the end: in run()
            self.checkpoint_and_flush()
        if p.step % 100 == 0:
            bar.update(p.step - bar.n)
        return False


class OfflineTrainer(Trainer):
    """The loop for offline agents: gradient steps on a fixed dataset, no env steps.

    The x-axis (``step`` of every metric, ``total_steps``, ``eval_every`` ...) counts gradient
    steps. Each evaluation runs ``eval_episodes`` per target return of the agent; the first target
    is the headline (``eval/return_mean``), every target is also logged on its own
    (``eval/target_<R>/return_mean``), and, when the dataset has reference returns, as a
    normalized score (0: random policy, 100: the dataset's behaviour policy).
    """

    x_axis = GRADIENT_STEPS
    rate_metric = "perf/gradient_steps_per_s"
    unit = "grad step"

    def __init__(self, *args, normalize: Callable[[float], float | None] | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.normalize = normalize or (lambda _: None)

    def _loop(self, bar: tqdm) -> None:
        p = self.progress
        while p.step < self.settings.total_steps:
            losses = self.agent.update()
            p.step += 1
            if self.after_step(losses, bar):
                return

    def evaluate(self) -> float:
        agent, extra, headline = self.agent, {}, None
        for target in agent.target_returns:
            agent.target_return = target
            returns = run_episodes(agent, self.eval_env, self.eval_start_seeds)
            name = f"eval/target_{target:g}"
            extra[f"{name}/return_mean"] = float(returns.mean())
            score = self.normalize(float(returns.mean()))
            if score is not None:
                extra[f"{name}/normalized_score"] = score
            headline = returns if headline is None else headline
        agent.target_return = agent.target_returns[0]
        score = self.normalize(float(headline.mean()))
        if score is not None:
            extra["eval/normalized_score"] = score
        return self._record_evaluation(headline, extra)

    def summary(self) -> dict[str, float]:
        summary = super().summary()
        score = self.normalize(summary.get("final/return_mean", float("nan")))
        if score is not None:
            summary["final/normalized_score"] = score
        return summary
