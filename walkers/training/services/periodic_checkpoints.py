"""Every ``checkpoint_every`` steps before the last: ``last.pt``, and a flush (the last step's
checkpoint is written by the book's ``finish``)."""

from __future__ import annotations

from walkers.training.services.service import RunService


class PeriodicCheckpoints(RunService):
    def every(self, settings) -> int:
        return settings.checkpoint_every

    def after_step(self, book, losses) -> bool:
        p, s = book.progress, book.settings
        if p.step % s.checkpoint_every == 0 and p.step < s.total_steps:
            book.checkpoint_and_flush()
        return False
