"""The NaN/inf guard every agent shares: skipped updates, counted on the device.

An update whose loss is not finite is skipped (the caller makes the optimizer step a no-op) and
counted. Counting happens in device tensors, so the guard adds no host-device sync to the hot
loop; the trainer reads ``health/*`` only when it logs, and ends a run whose updates have all been
skipped for too long (:class:`walkers.trainer.TrainingDiverged`).
"""

from __future__ import annotations

import torch

SKIPPED = "health/skipped_updates"
SKIPPED_IN_A_ROW = "health/skipped_in_a_row"


class NonFiniteGuard:
    """Counters of shape ``shape``: ``()`` for one agent, ``(K,)`` for a population of K."""

    def __init__(self, device: torch.device, shape: tuple[int, ...] = ()):
        self.skipped = torch.zeros(shape, device=device)
        self.in_a_row = torch.zeros(shape, device=device)

    @staticmethod
    def is_bad(*values: torch.Tensor) -> torch.Tensor:
        """1.0 if any of ``values`` is NaN/inf, else 0.0 (a device tensor, no sync)."""
        finite = torch.isfinite(values[0]).all()
        for value in values[1:]:
            finite &= torch.isfinite(value).all()
        return (~finite).to(torch.float32)

    @staticmethod
    def bad_members(*values: torch.Tensor) -> torch.Tensor:
        """Per member (the first dimension of each value): 1.0 where any is NaN/inf."""
        finite = torch.isfinite(values[0])
        for value in values[1:]:
            finite &= torch.isfinite(value)
        return (~finite).to(torch.float32)

    def record(self, bad: torch.Tensor) -> None:
        self.skipped += bad
        self.in_a_row = (self.in_a_row + bad) * bad  # reset by any good update

    def metrics(self) -> dict[str, torch.Tensor]:
        """The counters themselves, not copies: read when logged, they are current."""
        return {SKIPPED: self.skipped, SKIPPED_IN_A_ROW: self.in_a_row}

    def state_dict(self) -> dict:
        return {"skipped": self.skipped.tolist(), "in_a_row": self.in_a_row.tolist()}

    def load_state_dict(self, state: dict) -> None:
        self.skipped.copy_(torch.as_tensor(state["skipped"]))
        self.in_a_row.copy_(torch.as_tensor(state["in_a_row"]))
