"""walkers' Hydra plugins, as Hydra registers them: the A/B study sweeper (``ab=NAME``), the
Optuna sweeper of ``sweeps/`` (``hydra/sweeper=walkers``) and the plain multirun's.

Hydra imports every registered plugin (pyproject's ``hydra.plugins`` entry points) whenever it
composes a config: for every command, including one it refuses in one line because of a typo.
The sweepers themselves (:mod:`walkers.ab.sweeper`, :mod:`walkers.tuning.sweeper`) import torch,
MLflow, Optuna and SciPy, seconds of work on a loaded core. The classes here import nothing of
that: each builds its sweeper when a multirun instantiates it, and hands it every call, with a
config loader whose compositions a stop signal waits for
(:class:`walkers.interrupts.ShieldedConfigLoader`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from hydra.plugins.sweeper import Sweeper
from omegaconf import DictConfig

from walkers.interrupts import ShieldedConfigLoader


class _Deferred(Sweeper):
    """A sweeper whose implementation is imported when Hydra instantiates it."""

    def __init__(self, sweeper: Sweeper) -> None:
        self.sweeper = sweeper

    def setup(self, *, hydra_context, task_function, config: DictConfig) -> None:
        loader = ShieldedConfigLoader(hydra_context.config_loader)
        hydra_context = dataclasses.replace(hydra_context, config_loader=loader)
        self.sweeper.setup(hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> Any:
        return self.sweeper.sweep(arguments)


class ABStudySweeper(_Deferred):
    """An A/B study in rounds: :class:`walkers.ab.sweeper.StudySweeper`."""

    def __init__(self, **declared: Any) -> None:
        from walkers.ab.sweeper import StudySweeper

        super().__init__(StudySweeper(**declared))


class PruningOptunaSweeper(_Deferred):
    """An Optuna study with pruning, resumes and MLflow parent runs:
    :class:`walkers.tuning.sweeper.OptunaStudySweeper`."""

    def __init__(self, **settings: Any) -> None:
        from walkers.tuning.sweeper import OptunaStudySweeper

        super().__init__(OptunaStudySweeper(**settings))


class PlainSweeper(_Deferred):
    """A plain multirun (``-m a=1,2``): Hydra's own basic sweeper with the stop-safe config
    loader every walkers sweeper gets (``conf/hydra/sweeper/basic.yaml`` stands in for Hydra's
    ``hydra/sweeper=basic``)."""

    def __init__(self, **settings: Any) -> None:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

        super().__init__(BasicSweeper(**settings))
