"""A stop signal that arrives while a sweep's driver composes a job's config waits for the
composition's end, then stops the driver as a KeyboardInterrupt (130, KILLED), never as the
ConfigCompositionException or AttributeError OmegaConf makes of an interrupt inside a half-built
node (a study stopped between two jobs ended 1 and FAILED: CI, stop 59).

Real compositions of walkers' configs by Hydra's own loader, as walkers' sweepers hand it to
their launchers, and real timer signals through walkers' handler at spread-out moments.
"""

from __future__ import annotations

import random
import signal
import time

import pytest
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, RunMode

from walkers import CONF_DIR, interrupts
from walkers.plugins import _Deferred

pytestmark = pytest.mark.faults  # `make test-faults`: signals to this process, ~100 compositions


class _Keeps(Sweeper):
    """A sweeper that keeps the context walkers' plugin layer sets it up with."""

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.hydra_context = hydra_context

    def sweep(self, arguments):
        raise AssertionError("not swept here")


@pytest.fixture
def sweepers_loader():
    """Hydra's config loader for conf/, as walkers' sweepers (and so their launchers) get it."""
    with initialize_config_dir(config_dir=str(CONF_DIR)):
        hydra_loader = GlobalHydra.instance().config_loader()
        master = hydra_loader.load_configuration("train", [], run_mode=RunMode.MULTIRUN)
        kept = _Keeps()
        context = HydraContext(config_loader=hydra_loader, callbacks=None)
        _Deferred(kept).setup(hydra_context=context, task_function=None, config=master)
        yield kept.hydra_context.config_loader, master


def _composition_seconds(loader, master) -> float:
    """The median of three undisturbed compositions on this machine, to aim the timers by."""
    times = []
    for _ in range(3):
        start = time.perf_counter()
        loader.load_sweep_config(master, ["algo=sac", "env=hopper", "seed=0"])
        times.append(time.perf_counter() - start)
    return sorted(times)[1]


def test_a_signal_inside_a_jobs_composition_stops_the_driver_after_it(sweepers_loader):
    loader, master = sweepers_loader
    # Timers spread over four compositions' time: about a quarter fire inside one, the rest
    # after it (cancelled). A fixed spread missed every end on a slow CI machine (stop 62).
    latest = 4 * _composition_seconds(loader, master)
    before = signal.getsignal(signal.SIGALRM)
    moments = random.Random(0)
    outcomes = {"composed": 0, "interrupted": 0}
    try:
        for seed in range(100):
            signal.signal(signal.SIGALRM, interrupts._Stopping())  # a fresh driver's handler
            signal.setitimer(signal.ITIMER_REAL, moments.uniform(0.0005, latest))
            try:
                cfg = loader.load_sweep_config(master, ["algo=sac", "env=hopper", f"seed={seed}"])
                signal.setitimer(signal.ITIMER_REAL, 0)
                assert cfg.seed == seed and cfg.env.id == "Hopper-v5"
                outcomes["composed"] += 1
            except KeyboardInterrupt:  # anything else fails the test: the bug
                outcomes["interrupted"] += 1
            assert not interrupts.shielding()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, before)
    # both cases were met: signals inside compositions and compositions the timer missed
    assert outcomes["composed"] > 0 and outcomes["interrupted"] > 0, outcomes
