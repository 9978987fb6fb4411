"""Hydra callbacks (registered in ``conf/train.yaml`` under ``hydra.callbacks``)."""

from __future__ import annotations

import logging
import socket
import sys
import tempfile
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from walkers import tracking

log = logging.getLogger("walkers")


class PrepareTrackingStore(Callback):
    """Create the MLflow store and experiment once, before a multirun's jobs start.

    Jobs launched in parallel on a fresh sqlite store otherwise race on its schema creation
    ("duplicate column name") and on creating the experiment ("database is locked").
    """

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        check_ray_cluster(config.hydra.launcher)
        if not str(config.tracking.uri).startswith("sqlite:"):
            return  # a server creates its schema once and handles concurrent clients
        if "walkers.tuning" in str(config.hydra.sweeper.get("_target_", "")):
            return  # walkers' sweeper prepares the store itself, once its study is checked
        try:
            client = tracking.connect(config.tracking.uri)
            tracking.get_or_create_experiment(client, config.tracking.experiment)
        except Exception as e:  # each job reports a bad store itself, as a one-line error
            log.warning("could not prepare the MLflow store before the jobs: %s", e)


def check_ray_cluster(launcher: DictConfig) -> None:
    """With the Ray launcher on an existing cluster, the cluster must answer before any study or
    run is created: otherwise one ``error:`` line naming the address, exit 2."""
    if "hydra_ray_launcher" not in str(launcher.get("_target_", "")):
        return
    address = OmegaConf.select(launcher, "ray.init.address")
    if address in (None, "local"):  # the launcher starts a Ray of its own on this machine
        return
    if address == "auto":
        current = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
        if current.is_file():
            return
        reason = "no Ray cluster is running on this machine"
    else:
        host, _, port = str(address).removeprefix("ray://").rpartition(":")
        try:
            socket.create_connection((host, int(port)), timeout=3).close()
            return
        except (OSError, ValueError) as e:
            reason = f"{type(e).__name__}: {e}"
    print(
        f"error: hydra.launcher.ray.init.address={address!r} cannot be reached ({reason}); start "
        "the cluster (`ray start --head --port 6379`) or pass its head as "
        "hydra.launcher.ray.init.address=<host>:<port> (or RAY_ADDRESS)",
        file=sys.stderr,
    )
    sys.exit(2)
