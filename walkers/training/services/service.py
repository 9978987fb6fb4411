"""What a run service is (:mod:`walkers.training.services`)."""

from __future__ import annotations

import torch


class RunService:
    """One job of a run's book, done after each step it is due at. ``book`` is the run's
    :class:`~walkers.training.bookkeeping.RunBook` (which imports the services, not they it)."""

    def every(self, settings) -> int:
        """The steps this service may have work at are the multiples of this (and, for the
        evaluations, the budget's last step): the book skips it at every other step."""
        raise NotImplementedError

    def start(self, book, now: float) -> None:
        """A session of the run starts at ``now`` (``time.perf_counter()``), at the book's step."""

    def after_step(self, book, losses: dict[str, torch.Tensor]) -> bool:
        """After the book's current step: do the job if it is due; True stops the run."""
        raise NotImplementedError
