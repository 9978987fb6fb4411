"""A run's services are chosen by its settings, in the order a step's round runs them."""

from __future__ import annotations

from dataclasses import replace

from walkers.training.services import chosen_services
from walkers.training.services.evaluations import Pruning
from walkers.training.services.videos import Videos
from walkers.training.settings import RunSettings


def names(services) -> list[str]:
    return [type(service).__name__ for service in services]


def test_the_default_run_logs_watches_evaluates_and_checkpoints():
    assert names(chosen_services(RunSettings())) == [
        "MetricsLog",
        "DivergenceWatch",
        "Evaluations",
        "PeriodicCheckpoints",
    ]


def test_videos_and_pruning_come_when_asked_for_before_the_checkpoints():
    def stop_at_once(step: int, mean: float) -> bool:
        return True

    services = chosen_services(replace(RunSettings(), video_every=500), stop_at_once)
    assert names(services)[-3:] == ["Pruning", "Videos", "PeriodicCheckpoints"]
    pruning, videos = services[-3], services[-2]
    assert isinstance(pruning, Pruning) and pruning.on_evaluation is stop_at_once
    assert isinstance(videos, Videos) and videos.every(RunSettings()) == 500
