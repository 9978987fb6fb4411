"""Every ``log_every`` steps: a run whose last ``divergence_patience`` updates all had a NaN/inf
loss or gradient (each skipped by the NaN guard, :mod:`walkers.agents.common.health`) ends
FAILED, tagged with the step, its last good checkpoint kept."""

from __future__ import annotations

from walkers.agents.common.health import SKIPPED_IN_A_ROW
from walkers.training.provenance import DIVERGED_TAG
from walkers.training.services.service import RunService


class TrainingDiverged(RuntimeError):
    """Every update for ``divergence_patience`` updates in a row had a NaN/inf loss."""


class DivergenceWatch(RunService):
    def every(self, settings) -> int:
        return settings.log_every

    def after_step(self, book, losses) -> bool:
        step = book.progress.step
        if step % book.settings.log_every or SKIPPED_IN_A_ROW not in losses:
            return False
        in_a_row = float(losses[SKIPPED_IN_A_ROW])
        if in_a_row < book.settings.divergence_patience:
            return False
        named = ", ".join(f"{k}={float(v)}" for k, v in losses.items() if k.startswith("loss/"))
        kept = (
            f"checkpoints/last.pt (step {book.last_checkpoint_step}) is the last good one"
            if book.last_checkpoint_step is not None
            else "no checkpoint had been written yet"
        )
        book.run.set_tags({DIVERGED_TAG: str(step)})
        raise TrainingDiverged(
            f"training diverged at step {step}: the last {int(in_a_row)} updates all had a "
            f"NaN/inf loss or gradient ({named}) and were skipped; {kept}"
        )
