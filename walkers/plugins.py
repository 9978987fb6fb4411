"""walkers' Hydra plugins, as Hydra registers them: the A/B study sweeper (``ab=NAME``), the
Optuna sweeper of ``sweeps/`` (``hydra/sweeper=walkers``) and the plain multirun's.

Hydra imports every registered plugin (pyproject's ``hydra.plugins`` entry points) whenever it
composes a config: for every command, including one it refuses in one line because of a typo.
The sweepers themselves (:mod:`walkers.ab.study_sweeper`, :mod:`walkers.tuning.optuna_sweeper`)
import torch,
MLflow, Optuna and SciPy, seconds of work on a loaded core. The classes here import nothing of
that: each builds its sweeper when a multirun instantiates it, and hands it every call, with a
config loader whose compositions a stop signal waits for
(:class:`walkers.interrupts.ShieldedConfigLoader`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from hydra.plugins.sweeper import Sweeper
from omegaconf import DictConfig, OmegaConf

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
    """An A/B study in rounds: :class:`walkers.ab.study_sweeper.StudySweeper`."""

    def __init__(self, **declared: Any) -> None:
        from walkers.ab.study_sweeper import StudySweeper

        super().__init__(StudySweeper(**declared))


class PruningOptunaSweeper(_Deferred):
    """An Optuna study with pruning, resumes and MLflow parent runs:
    :class:`walkers.tuning.optuna_sweeper.OptunaStudySweeper`."""

    def __init__(self, **settings: Any) -> None:
        from walkers.tuning.optuna_sweeper import OptunaStudySweeper

        super().__init__(OptunaStudySweeper(**settings))


#: the stores whose schema MLflow migrates from the client (a server migrates its own)
DATABASES = {"sqlite", "postgresql", "mysql", "mssql"}


class PlainSweeper(_Deferred):
    """A plain multirun (``-m a=1,2``): Hydra's own basic sweeper with the stop-safe config
    loader every walkers sweeper gets (``conf/hydra/sweeper/basic.yaml`` stands in for Hydra's
    ``hydra/sweeper=basic``)."""

    def __init__(self, **settings: Any) -> None:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

        super().__init__(BasicSweeper(**settings))

    def setup(self, *, hydra_context, task_function, config: DictConfig) -> None:
        super().setup(hydra_context=hydra_context, task_function=task_function, config=config)
        self.store = OmegaConf.select(
            config, "tracking.uri", default=None, throw_on_resolution_failure=False
        )

    def sweep(self, arguments: list[str]) -> Any:
        if isinstance(self.store, str) and self.store.split(":")[0].split("+")[0] in DATABASES:
            # A new database store's schema is made here, once, before the jobs: jobs launched
            # together (joblib) into a sqlite store nobody had opened each ran MLflow's
            # migrations, and all but one failed (3 of 4 on 2 cores). The study and Optuna
            # sweepers open their store first too. An unusable store is one line here.
            from walkers.cli import or_exit
            from walkers.tracking.client import connect

            or_exit(connect, self.store)
        return super().sweep(arguments)
