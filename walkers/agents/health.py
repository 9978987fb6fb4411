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
    def __init__(self, device: torch.device):
        self.skipped = torch.zeros((), device=device)
        self.in_a_row = torch.zeros((), device=device)

    @staticmethod
    def is_bad(*values: torch.Tensor) -> torch.Tensor:
        """1.0 if any of ``values`` is NaN/inf, else 0.0 (a device tensor, no sync)."""
        finite = torch.isfinite(values[0]).all()
        for value in values[1:]:
            finite &= torch.isfinite(value).all()
        return (~finite).to(torch.float32)

    def record(self, bad: torch.Tensor) -> None:
        self.skipped += bad
        self.in_a_row = (self.in_a_row + bad) * bad  # reset by any good update

    def metrics(self) -> dict[str, torch.Tensor]:
        """The counters themselves, not copies: read when logged, they are current."""
        return {SKIPPED: self.skipped, SKIPPED_IN_A_ROW: self.in_a_row}

    def state_dict(self) -> dict:
        return {"skipped": self.skipped.item(), "in_a_row": self.in_a_row.item()}

    def load_state_dict(self, state: dict) -> None:
        self.skipped.fill_(state["skipped"])
        self.in_a_row.fill_(state["in_a_row"])
