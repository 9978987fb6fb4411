"""Every aggregate, P(A > B) and their CIs are rliable's own: on a table of three tasks with
unequal seeds per arm (:mod:`tests.analysis.rliable_reference`), against the numbers rliable
1.2.0 computed (``rliable_reference.json``) and, in ``make test-slow``, against rliable itself,
installed apart (it does not install beside pandas 3)."""

from __future__ import annotations

import json
import subprocess
import venv
from pathlib import Path

import numpy as np
import pytest

from tests.analysis.rliable_reference import SCORES
from walkers import PROJECT_ROOT
from walkers.analysis import stats

PINNED = json.loads((Path(__file__).with_name("rliable_reference.json")).read_text())
#: how far two 20,000-draw percentile bootstraps of these few seeds fall apart: a few steps of
#: the statistics' own grain (normalized points), and one step of P(A > B)'s, which over three
#: tasks of 5 x 3 pairs moves in steps of 1/45
CI_NOISE, P_NOISE = 0.6, 1 / 45 + 1e-9
#: rliable's draws in the live test (its 20,000 take 47 s of a CPU core; these about 12), whose
#: P(A > B) ends may then fall two steps of its grain away
LIVE_REPS, LIVE_P_NOISE = 5000, 2 / 45 + 1e-9


def _per_task(arm: str) -> dict[str, np.ndarray]:
    matrix = np.array(SCORES[arm])
    return {f"task{j}": matrix[:, j] for j in range(matrix.shape[1])}


def ours() -> dict:
    out = {
        arm: {
            name: list(ci)
            for name, ci in stats.aggregate_cis(_per_task(arm), n_resamples=20_000).items()
        }
        for arm in SCORES
    }
    p = stats.average_improvement(_per_task("A"), _per_task("B"), n_resamples=20_000)
    return out | {"P(A > B)": list(p)}


def assert_like(theirs: dict, mine: dict, p_noise: float = P_NOISE) -> None:
    """Points to the last digit; CIs within the bootstrap's own noise."""
    for arm in SCORES:
        for name, (point, low, high) in theirs[arm].items():
            assert mine[arm][name][0] == pytest.approx(point, rel=1e-12), (arm, name)
            assert mine[arm][name][1:] == pytest.approx([low, high], abs=CI_NOISE), (arm, name)
    point, low, high = theirs["P(A > B)"]
    assert mine["P(A > B)"][0] == pytest.approx(point, rel=1e-12)
    assert mine["P(A > B)"][1:] == pytest.approx([low, high], abs=p_noise)


def test_every_aggregate_and_ci_is_what_rliable_computed():
    assert set(map(len, SCORES.values())) == {5, 3} and len(SCORES["A"][0]) == 3
    assert_like(PINNED, ours())


@pytest.mark.slow  # `make test-slow`: rliable itself, in an environment of its own
def test_every_aggregate_and_ci_is_rliable_s_own_live(tmp_path):
    env = tmp_path / "rliable"
    venv.create(env, with_pip=True)
    python = env / "bin" / "python"
    install = subprocess.run(
        [python, "-m", "pip", "install", "-q", "rliable==1.2.0", "pandas<3"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if install.returncode != 0:
        pytest.skip(f"rliable 1.2.0 does not install here: {install.stderr[-300:]}")
    live = subprocess.run(
        [python, "-m", "tests.analysis.rliable_reference", str(LIVE_REPS)],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert live.returncode == 0, live.stderr[-2000:]
    theirs = json.loads(live.stdout)
    assert_like(theirs, ours(), LIVE_P_NOISE)
    assert_like(theirs, PINNED, LIVE_P_NOISE)  # the pinned numbers are rliable's, within its noise
