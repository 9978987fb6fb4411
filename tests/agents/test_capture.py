"""``algo.capture``: the whole off-policy update as CUDA graphs computes the eager update, update
after update; ``auto`` (the default) captures on CUDA unless ``compile`` is on, and on a CPU the
flag changes nothing. The CUDA tests run with `make test-gpu`
on a GPU machine and skip elsewhere."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from tests.conftest import compose_cfg, filled_agent
from walkers.agents.base import Transition
from walkers.agents.common.capture import WARMUP_UPDATES, CapturedUpdate
from walkers.agents.crossq import CrossQ
from walkers.agents.ddpg import DDPG
from walkers.agents.sac import SAC
from walkers.agents.td3 import TD3
from walkers.agents.td7 import TD7
from walkers.errors import ConfigError
from walkers.training.settings import validate

OBS, ACT = 5, 2  # filled_agent's shapes
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (make test-gpu)")


def filled(cls, device: str, capture: bool | str, population: int = 1, **settings):
    """A small agent with the same seed and the same 200 stored transitions, nothing updated."""
    wide = {"critic_hidden_sizes": [64, 64], "renorm_warmup_steps": 10} if cls is CrossQ else {}
    if cls is TD7:  # small, with hard target copies among the first updates
        wide = {"zs_dim": 16, "encoder_hidden_sizes": [32, 32], "target_update_rate": 4}
    return filled_agent(cls, population, device, capture=capture, **wide, **settings)


def test_capture_on_a_cpu_runs_the_eager_update_and_says_so(caplog):
    with caplog.at_level(logging.WARNING, logger="walkers"):
        flagged = filled(TD3, "cpu", capture=True)
    assert "algo.capture=true needs CUDA: on cpu the update runs eagerly" in caplog.text
    assert not isinstance(flagged.update, CapturedUpdate)
    plain = filled(TD3, "cpu", capture=False)
    for _ in range(4):
        a, b = flagged.update(), plain.update()
        assert all(torch.equal(a[key], b[key]) for key in a)


@pytest.mark.parametrize(
    "device, compile, captured",
    [
        ("cpu", False, False),
        pytest.param("cuda", False, True, marks=CUDA),
        pytest.param("cuda", True, False, marks=CUDA),
    ],
)
def test_capture_auto_captures_on_cuda_unless_compiled(caplog, device, compile, captured):
    with caplog.at_level(logging.WARNING, logger="walkers"):
        agent = filled(TD3, device, capture="auto", compile=compile)
    assert isinstance(agent.update, CapturedUpdate) == captured
    assert "needs CUDA" not in caplog.text  # auto asks for nothing the device lacks


def test_a_bad_capture_value_names_the_allowed_ones():
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.capture=yes"])
    with pytest.raises(ConfigError, match="algo.capture='yes'.*auto, true or false"):
        validate(cfg)


def test_capture_and_compile_together_are_refused_in_one_line():
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.capture=true", "algo.compile=true"])
    with pytest.raises(ConfigError, match="algo.capture=true is not allowed with algo.compile"):
        validate(cfg)


@CUDA
@pytest.mark.parametrize("cls", [TD3, DDPG, SAC, CrossQ, TD7])
@pytest.mark.parametrize("population", [1, 3])
def test_captured_updates_follow_the_eager_ones(cls, population):
    eager = filled(cls, "cuda", capture=False, population=population)
    captured = filled(cls, "cuda", capture=True, population=population)
    step = getattr(captured, captured.captured_step)  # the update, or (TD7) its graphed part
    assert isinstance(step, CapturedUpdate)
    for n in range(WARMUP_UPDATES + 3 * max(2, captured.update_period)):
        expected, got = eager.update(), captured.update()
        assert set(got) == set(expected), n
        for key in expected:
            torch.testing.assert_close(got[key], expected[key], rtol=1e-4, atol=1e-5)
    assert captured.num_updates == eager.num_updates
    assert len(step.graphs) == captured.update_period  # one graph per way through
    for name in ("actor", "critic"):
        mine = getattr(captured, name).state_dict()
        for key, value in getattr(eager, name).state_dict().items():
            torch.testing.assert_close(mine[key], value, rtol=1e-4, atol=1e-5)
    # the buffer goes on growing under the captured sampler: the graph reads its size
    captured.observe_population(
        [Transition(np.zeros(OBS), np.zeros(ACT), 0.0, np.zeros(OBS), False, False)] * population
    )
    eager.observe_population(
        [Transition(np.zeros(OBS), np.zeros(ACT), 0.0, np.zeros(OBS), False, False)] * population
    )
    got, expected = captured.update(), eager.update()
    torch.testing.assert_close(got["loss/critic"], expected["loss/critic"], rtol=1e-4, atol=1e-5)


@CUDA
def test_a_captured_run_resumes_on_a_cpu_and_the_other_way_round():
    captured = filled(TD3, "cuda", capture=True)
    for _ in range(WARMUP_UPDATES + 4):
        captured.update()
    state = captured.state_dict(with_buffer=True)
    on_cpu = filled(TD3, "cpu", capture=False)
    on_cpu.load_state_dict(state)
    back = filled(TD3, "cuda", capture=True)
    back.load_state_dict(on_cpu.state_dict(with_buffer=True))
    a, b = on_cpu.update(), captured.update()
    torch.testing.assert_close(a["loss/critic"], b["loss/critic"].cpu(), rtol=1e-4, atol=1e-5)
    for _ in range(WARMUP_UPDATES + 2):
        back.update()  # warms up and captures from a loaded state
    assert back.num_updates == captured.num_updates - 1 + WARMUP_UPDATES + 2
