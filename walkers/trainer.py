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
from walkers.stats import run_summary
from walkers.tracking import Tracker
from walkers.video import write_gif

EVAL_SEED_OFFSET = 10_000


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

    # --- checkpoints --------------------------------------------------------------------------
    def restore(self, state: dict) -> None:
        """Continue from a checkpoint written by this class."""
        self.agent.load_state_dict(state["agent"])
        self.progress = Progress(**state["trainer"])
        self.last_checkpoint_step = self.progress.step
        torch.set_rng_state(state["torch_rng"])

    def save_checkpoint(self, name: str = "last.pt") -> Path:
        with_buffer = self.settings.save_buffer and name == "last.pt"
        state = {
            "agent": self.agent.state_dict(with_buffer=with_buffer),
            "trainer": dataclasses.asdict(self.progress),
            "torch_rng": torch.get_rng_state(),
            **self.checkpoint_extra,
        }
        path = checkpoints.save(state, self.checkpoint_dir / name)
        self.tracker.log_artifact(path, "checkpoints")
        return path

    def _checkpoint_and_flush(self) -> None:
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
        p, s = self.progress, self.settings
        returns = run_episodes(
            self.agent, self.eval_env, s.eval_episodes, s.seed + EVAL_SEED_OFFSET
        )
        mean = float(returns.mean())
        p.eval_steps.append(p.step)
        p.eval_means.append(mean)
        self.tracker.log_metrics(
            {"eval/return_mean": mean, "eval/return_std": float(returns.std())}, p.step
        )
        if mean > p.best_eval:
            p.best_eval = mean
            self.save_checkpoint("best.pt")
        return mean

    def record_video(self) -> None:
        """Log a gif of one greedy episode (from the first eval start state) to ``videos/``."""
        _, frames, fps = record_episodes(
            self.agent, self.video_env, 1, self.settings.seed + EVAL_SEED_OFFSET
        )
        path = self.checkpoint_dir.parent / "videos" / f"step_{self.progress.step:08d}.gif"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_gif(frames[:TRAINING_GIF_FRAMES], path, fps)
        self.tracker.log_artifact(path, "videos")

    # --- the loop -----------------------------------------------------------------------------
    def run(self) -> dict[str, float]:
        """Train until ``total_steps``; returns the ``final/*`` and ``perf/sps`` metrics.

        On KeyboardInterrupt (Ctrl-C, or SIGTERM turned into one) a last checkpoint is saved
        before the exception propagates.
        """
        s, p, agent, env, tracker = self.settings, self.progress, self.agent, self.env, self.tracker
        # A fresh run seeds its first reset with `seed`; a resumed one starts a new episode seeded
        # by the episode count (an interrupted episode cannot be continued).
        obs, _ = env.reset(seed=s.seed + p.episodes)
        bar = tqdm(
            total=s.total_steps,
            initial=p.step,
            unit="step",
            disable=not s.progress,
            dynamic_ncols=True,
            mininterval=1.0,
        )
        start_step, start_time = p.step, time.perf_counter()
        log_step, log_time = p.step, start_time
        losses: dict[str, torch.Tensor] = {}
        try:
            while p.step < s.total_steps:
                action = agent.act(obs, explore=True)
                next_obs, reward, terminated, truncated, info = env.step(action)
                agent.observe(
                    Transition(obs, action, float(reward), next_obs, terminated, truncated)
                )
                losses.update(agent.update())
                p.step += 1
                obs = next_obs
                if terminated or truncated:
                    p.episodes += 1
                    episode = info["episode"]  # true return, recorded before any reward shaping
                    tracker.log_metrics(
                        {
                            "train/episode_return": episode["r"],
                            "train/episode_length": episode["l"],
                        },
                        p.step,
                    )
                    obs, _ = env.reset()
                if p.step % s.log_every == 0:
                    now = time.perf_counter()
                    sps = (p.step - log_step) / (now - log_time)
                    log_step, log_time = p.step, now
                    scalars = {k: v.item() for k, v in losses.items()}
                    tracker.log_metrics({"perf/sps": sps, **scalars}, p.step)
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
                        break
                if s.video_every and p.step % s.video_every == 0:
                    self.record_video()
                if p.step % s.checkpoint_every == 0 and p.step < s.total_steps:  # end: below
                    self._checkpoint_and_flush()
                if p.step % 100 == 0:
                    bar.update(p.step - bar.n)
        except KeyboardInterrupt:
            self._checkpoint_and_flush()
            raise
        finally:
            bar.close()
        elapsed = time.perf_counter() - start_time
        summary = run_summary(p.eval_steps, p.eval_means, s.threshold)
        if p.step > start_step:
            summary["perf/sps"] = (p.step - start_step) / elapsed
        tracker.log_metrics(summary, p.step)
        self._checkpoint_and_flush()
        return summary
