"""A run's services: the jobs its book does after the steps they are due at, one job each.

    MetricsLog          every log_every steps: losses, throughput, CPU-hours
    DivergenceWatch     every log_every steps: ends a run whose updates have all been skipped
    Evaluations         every eval_every steps and at the last: eval/*, best.pt
    Pruning             after an evaluation: a sweep's pruner may stop the trial (when asked)
    Videos              every video_every steps: a gif of the greedy policy (when video_every > 0)
    PeriodicCheckpoints every checkpoint_every steps: last.pt (the end's is the book's finish)

:func:`chosen_services` picks them from the run's settings, in that order: a service that stops
the run (a pruned trial) ends the step's round, as the book runs them in turn.
"""

from __future__ import annotations

from collections.abc import Callable

from walkers.training.services.divergence import DivergenceWatch, TrainingDiverged
from walkers.training.services.evaluations import Evaluations, Pruning
from walkers.training.services.metrics_log import MetricsLog
from walkers.training.services.periodic_checkpoints import PeriodicCheckpoints
from walkers.training.services.service import RunService
from walkers.training.services.videos import Videos
from walkers.training.settings import RunSettings

__all__ = ["RunService", "TrainingDiverged", "chosen_services"]


def chosen_services(
    settings: RunSettings, on_evaluation: Callable[[int, float], bool] | None = None
) -> list[RunService]:
    """The services a run with ``settings`` has; ``on_evaluation`` (a sweep trial's pruner
    callback, ``(step, eval mean) -> stop?``) adds pruning."""
    services: list[RunService] = [MetricsLog(), DivergenceWatch(), Evaluations()]
    if on_evaluation is not None:
        services.append(Pruning(on_evaluation))
    if settings.video_every:
        services.append(Videos(settings.video_every))
    services.append(PeriodicCheckpoints())
    return services
