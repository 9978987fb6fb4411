"""The progress bar's time left: an off-policy run's warm-up (random actions, no updates) runs
many times faster than its learning phase, so the bar counts each phase at its own rate."""

from __future__ import annotations

import re

from tqdm import tqdm

from tests.conftest import run_cli
from walkers.training.loops import ProgressBar


def test_the_time_left_counts_the_learning_phase_at_its_own_rate():
    bar = ProgressBar(total=1_000_000, learning_from=25_000, disable=True)
    assert bar.eta(0, now=0.0) == {"eta": "after the warm-up to step 25,000"}
    assert bar.eta(24_900, now=59.0) == {"eta": "after the warm-up to step 25,000"}
    assert bar.eta(25_000, now=60.0) == {"eta": "measuring the learning phase"}
    # 1,000 learning steps in 10 s: 100 steps/s for the 974,000 left (the warm-up's 400/s unused)
    assert bar.eta(26_000, now=70.0) == {"eta": tqdm.format_interval(9_740)}
    assert bar.eta(26_000, now=70.0)["eta"] == "2:42:20"
    assert bar.eta(1_000_000, now=1e4) == {}


def test_a_run_that_resumes_past_its_warm_up_measures_from_its_first_step():
    bar = ProgressBar(total=10_000, learning_from=1_000, disable=True)
    assert bar.eta(5_000, now=100.0) == {"eta": "measuring the learning phase"}
    assert bar.eta(6_000, now=110.0) == {"eta": "00:40"}  # 4,000 left at 100 steps/s


def test_an_on_policy_run_has_no_warm_up(tmp_path):
    bar = ProgressBar(total=2_048, learning_from=0, disable=True)
    assert bar.eta(0, now=0.0) == {"eta": "measuring the learning phase"}


def test_a_run_s_bar_opens_saying_when_learning_starts(store):
    args = ["algo=td3", "env=pendulum", "total_steps=400", "eval_every=400", "eval_episodes=1",
            "algo.learning_starts=300", "algo.hidden_sizes=[16,16]", "algo.batch_size=32",
            "progress=true", *store["overrides"]]  # fmt: skip
    result = run_cli(args, cwd=store["path"])
    assert result.returncode == 0, result.stderr[-2000:]
    bars = [line for line in re.split(r"[\r\n]", result.stderr) if "/400 [" in line]
    assert "0/400 [" in bars[0] and "eta=after the warm-up to step 300" in bars[0], bars[0]
    assert "400/400" in bars[-1] and "eta=" not in bars[-1], bars[-1]
