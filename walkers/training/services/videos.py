"""Every ``video_every`` steps: a gif of one greedy episode, from the first evaluation start state,
logged to the run's ``videos/``."""

from __future__ import annotations

from walkers.training.greedy_episodes import record_episodes
from walkers.training.services.service import RunService
from walkers.training.video import write_gif

#: Frames kept in the gif (a glance, not a film).
TRAINING_GIF_FRAMES = 500


class Videos(RunService):
    def __init__(self, every: int):
        self.period = every

    def every(self, settings) -> int:
        return self.period

    def after_step(self, book, losses) -> bool:
        step = book.progress.step
        if step % self.period == 0:
            _, frames, fps = record_episodes(book.agent, book.video_env, book.eval_start_seeds[:1])
            path = book.run.folder.video(step)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_gif(frames[:TRAINING_GIF_FRAMES], path, fps)
            book.run.upload(path, "videos")
        return False
