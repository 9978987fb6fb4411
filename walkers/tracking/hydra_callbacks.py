"""Hydra callbacks (registered in ``conf/train.yaml`` under ``hydra.callbacks``)."""

from __future__ import annotations

import logging
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from walkers import tracking

log = logging.getLogger("walkers")


class PrepareTrackingStore(Callback):
    """Create the MLflow store and experiment once, before a multirun's jobs start.

    Jobs launched in parallel on a fresh sqlite store otherwise race on its schema creation
    ("duplicate column name") and on creating the experiment ("database is locked").
    """

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            client = tracking.connect(config.tracking.uri)
            tracking.get_or_create_experiment(client, config.tracking.experiment)
        except Exception as e:  # each job reports a bad store itself, as a one-line error
            log.warning("could not prepare the MLflow store before the jobs: %s", e)
