"""Every ``log_every`` steps: the step's losses, the throughput since the last log, CPU-hours."""

from __future__ import annotations

import time

from walkers.training.services.service import RunService

CPU_HOURS = "perf/cpu_hours"


class MetricsLog(RunService):
    def every(self, settings) -> int:
        return settings.log_every

    def start(self, book, now: float) -> None:
        self._step, self._time = book.progress.step, now

    def after_step(self, book, losses) -> bool:
        step = book.progress.step
        if step % book.settings.log_every:
            return False
        now = time.perf_counter()
        rate = (step - self._step) / (now - self._time)
        self._step, self._time = step, now
        scalars = {key: float(value) for key, value in losses.items()}  # tensors or floats
        book.run.log_metrics(
            {book.axis.rate_metric: rate, CPU_HOURS: book.cpu_hours(), **scalars}, step
        )
        return False
