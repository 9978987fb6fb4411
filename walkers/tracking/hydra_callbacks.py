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

from walkers.tracking.client import connect, end_running, get_or_create_experiment, quoted
from walkers.tracking.names import MULTIRUN_JOB_TAG, status_after

log = logging.getLogger("walkers")


class PrepareTrackingStore(Callback):
    """Create the MLflow store and experiment once, before a multirun's jobs start; end the runs
    its jobs leave behind if the multirun itself dies.

    Jobs launched in parallel on a fresh sqlite store otherwise race on its schema creation
    ("duplicate column name") and on creating the experiment ("database is locked"). A driver
    stopped by Ctrl-C (or SIGTERM) or by a launcher error takes its Ray jobs with it: on its way
    out, the runs of this multirun's jobs (tag ``walkers.multirun_job``: ``<sweep dir>#<n>``,
    whatever their ``job_key``) still RUNNING are ended (KILLED after Ctrl-C, else FAILED). A
    sweep's sweeper does the same for its own jobs, and tells their trials.
    """

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        check_ray_cluster(config.hydra.launcher)
        if not str(config.tracking.uri).startswith("sqlite:"):
            return  # a server creates its schema once and handles concurrent clients
        if str(config.hydra.sweeper.get("_target_", "")).startswith("walkers."):
            return  # walkers' sweepers (a tuning sweep, an A/B study) prepare the store
            # themselves, once their declaration is checked: bad input creates nothing
        try:
            client = connect(config.tracking.uri)
            get_or_create_experiment(client, config.tracking.experiment)
        except Exception as e:  # each job reports a bad store itself, as a one-line error
            log.warning("could not prepare the MLflow store before the jobs: %s", e)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Called on every way out of a multirun; ``sys.exc_info()`` holds what stopped it."""
        error = sys.exc_info()[1]
        if error is None or isinstance(error, SystemExit):
            return  # every job returned (each ended its own runs), or bad input started none
        stop_remote_jobs()
        status = status_after(error)
        try:
            client = connect(config.tracking.uri)
            jobs = quoted(f"{config.hydra.sweep.dir}#%")  # this multirun's jobs
            query = f"tags.`{MULTIRUN_JOB_TAG}` LIKE {jobs}"
            reason = f"its multirun stopped before the job ended: {type(error).__name__}"
            experiment = config.tracking.experiment
            for run_id in end_running(client, experiment, query, status, reason):
                log.warning("run %s of this multirun was left RUNNING: %s", run_id, status)
        except Exception as e:  # on the way out: say it, never mask why the multirun stopped
            log.error("could not end the runs of this multirun's jobs: %s", e)


def stop_remote_jobs() -> None:
    """Stop the jobs this process launched on a Ray cluster (its tasks end with the driver),
    so that no run is ended while its job still trains."""
    if "ray" in sys.modules:
        import ray

        if ray.is_initialized():
            ray.shutdown()


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


def missing_on_ray_nodes(launcher: DictConfig, names: list[str]) -> list[tuple[str, str]]:
    """``(node, variable)`` for each variable of ``names`` that a live node of the launcher's Ray
    cluster lacks in its environment: jobs read them there (a Ray worker has its node's
    environment as it was at ``ray start``). Ray is initialized with the launcher's own settings,
    which the launcher then finds in place."""
    if "hydra_ray_launcher" not in str(launcher.get("_target_", "")) or not names:
        return []
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    if not ray.is_initialized():
        init = OmegaConf.to_container(launcher.ray.init, resolve=True) or {}
        ray.init(**init)

    @ray.remote(num_cpus=0, max_retries=0)
    def probe(wanted: list[str]) -> list[str]:
        import os

        return [name for name in wanted if not os.environ.get(name)]

    nodes = [n for n in ray.nodes() if n.get("Alive")]
    asked = [
        probe.options(
            scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)
        ).remote(names)
        for n in nodes
    ]
    missing = []
    for node, answer in zip(nodes, asked, strict=True):
        where = f"{node.get('NodeManagerAddress')} (node {node['NodeID'][:12]})"
        try:
            missing += [(where, name) for name in ray.get(answer, timeout=120)]
        except Exception as e:  # a node going away: its jobs go elsewhere; never block on it
            log.warning("could not ask Ray node %s for its environment: %s", where, e)
    return missing
