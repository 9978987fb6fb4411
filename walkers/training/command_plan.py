"""What one training command will do, decided before anything is built: its :class:`Plan`.

    plan_command(cfg, overrides) -> Plan: new run(s) | run(s) to continue, each from its checkpoint
                                | nothing (the command's runs FINISHED)

Every way a run is continued is decided here, with :mod:`walkers.training.attempts` (the same
command run again) and :mod:`walkers.training.resume` (a named run):
``resume=`` given, a multirun job or a study's job run again (its ``job_key``), a plain command
run again (the same composed config, less what may change on resume), a population's members
together, an offline run's data checked, a run from before a hyperparameter was declared. The
config is checked once (:mod:`walkers.training.validate`): the command's before the store is
asked anything, and where a run continues, its stored config with the overrides it takes.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig

from walkers.tracking.client import connect
from walkers.training import attempts, resume
from walkers.training.checkpoints import Checkpoint
from walkers.training.provenance import COMMAND_KEY_TAG
from walkers.training.run_dataset import RunDataset, loader
from walkers.training.validate import check_command, is_offline, validate

log = logging.getLogger("walkers")


@dataclass(frozen=True)
class Plan:
    """One command's work: ``cfg``, the session's config (validated); ``members``, the config of
    each run it trains (one, or one per member of a population); ``starts``, the checkpoint each
    goes on from (None: a new run); ``data``, an offline run's data; ``finished``, the runs that
    already did what the command asks (then nothing is built); ``tags`` for new runs."""

    cfg: DictConfig
    client: object  # an MlflowClient of cfg.tracking.uri
    members: list[DictConfig]
    starts: list[Checkpoint | None]
    data: RunDataset | None
    new_run_tags: dict[str, str]
    finished: list | None = None

    @property
    def resumed(self) -> bool:
        return any(start is not None for start in self.starts)

    def finished_value(self) -> float:
        """The optimized metric of the runs that finished (their mean, for a population)."""
        values = [r.data.metrics.get(self.cfg.optimized_metric, math.nan) for r in self.finished]
        return float(np.mean(values))


def plan_command(cfg: DictConfig, overrides=()) -> Plan:
    """What ``cfg`` (a composed config; ``overrides``: its command-line overrides) will do."""
    check_command(cfg)  # before anything is read or created
    if not cfg.resume:
        validate(cfg)  # before the store is asked anything
    resumed = f"resume={cfg.resume!r}" if isinstance(cfg.resume, str) else f"resume={cfg.resume}"
    client = connect(cfg.tracking.uri, looking_for=resumed if cfg.resume else None)
    run_dataset = loader()
    attempt = attempts.of_command(client, cfg, run_dataset)
    cfg, new_run_tags = attempt.cfg, {COMMAND_KEY_TAG: attempt.key}
    if attempt.finished:
        return Plan(cfg, client, [], [], None, new_run_tags, finished=attempt.finished)
    if cfg.resume:  # a run's stored config, with the overrides it takes
        cfg, members = resume.resumed(client, cfg, overrides, run_dataset)
        validate(cfg)
    else:
        members = [(member, None) for member in attempt.members]
    data = run_dataset(cfg) if is_offline(cfg) else None
    starts = [start for _, start in members]
    return Plan(cfg, client, [member for member, _ in members], starts, data, new_run_tags)
