"""The suite report: rliable's aggregates checked against numbers computed by hand, and a real
report over tiny runs on two envs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import all_runs, one_line_error, run_cli
from walkers.analysis import stats


def test_the_aggregates_match_their_definitions_by_hand():
    x = np.array([10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0])
    # IQM: the mean of the middle half (30, 40, 50, 60); optimality gap: mean shortfall below 100
    assert stats.iqm(x) == pytest.approx(45.0)
    assert stats.optimality_gap(x) == pytest.approx(np.mean(100 - x))
    assert stats.optimality_gap(np.array([120.0, 80.0])) == pytest.approx(10.0)
    cis = stats.aggregate_cis({"a": x[:4], "b": x[4:]}, n_resamples=500)
    assert cis["mean"][0] == pytest.approx(45.0) and cis["median"][0] == pytest.approx(45.0)
    for point, low, high in cis.values():
        assert low <= point <= high


def test_the_bootstrap_is_stratified_by_env():
    # two envs whose scores never overlap: a stratified resample keeps half the runs in each, so
    # the pooled median stays between the envs; resampling across envs would not
    per_env = {"low": np.zeros(6), "high": np.full(6, 100.0)}
    _, low, high = stats.aggregate_cis(per_env, n_resamples=300)["mean"]
    assert low == high == 50.0


def test_probability_of_improvement_is_averaged_over_envs():
    a = {"e1": np.array([3.0, 4.0]), "e2": np.array([0.0, 1.0])}
    b = {"e1": np.array([1.0, 2.0]), "e2": np.array([0.0, 5.0])}
    # e1: A wins all 4 pairs (1.0); e2: (0>0 tie .5, 0<5, 1>0, 1<5) -> 1.5/4
    point, low, high = stats.average_improvement(a, b, n_resamples=300)
    assert point == pytest.approx((1.0 + 1.5 / 4) / 2)
    assert low <= point <= high


def test_holm_adjusts_step_down():
    adjusted = stats.holm({"a": 0.01, "b": 0.04, "c": 0.03})
    assert adjusted == pytest.approx({"a": 0.03, "c": 0.06, "b": 0.06})


def test_performance_profile_counts_runs_above_tau_each_task_weighed_alike():
    taus = np.array([-1.0, 25.0, 100.0])
    profile = stats.performance_profile({"a": np.array([0.0, 50.0, 100.0])}, taus)
    assert profile.tolist() == pytest.approx([1.0, 2 / 3, 0.0])
    # 1 seed above 25 of 1 on one env, 0 of 3 on the other: 1/2, not the pooled 1/4 (rliable)
    two = {"few": np.array([30.0]), "many": np.array([0.0, 10.0, 20.0])}
    assert stats.performance_profile(two, taus).tolist() == pytest.approx([1.0, 0.5, 0.0])


@pytest.mark.slow  # `make test-slow`: trains two envs (the default suite renders suite reports
# from their bundles: results/tiny, results/ppo_walker2d)
def test_a_suite_report_over_two_envs(store):
    runs = run_cli(
        ["-m", "algo=reinforce,td3", "env=pendulum,inverted_pendulum", "seed=0,1",
         "total_steps=300", "eval_every=100", "eval_episodes=1",
         "progress=false", "tracking.experiment=suite", *store["overrides"]],
        cwd=store["path"],
    )  # fmt: skip
    assert runs.returncode == 0, runs.stderr[-3000:]
    out = store["path"] / "reports"
    result = run_cli(
        ["envs=[pendulum,inverted_pendulum]", "tracking.experiment=suite", "n_resamples=200",
         "confidence=0.9", f"out={out}/suite_test/x", *store["overrides"]],
        cwd=store["path"],
        module="walkers.compare",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    suite_dir = out / "suite_test" / "suite"
    summary = json.loads((suite_dir / "summary.json").read_text())
    assert set(summary["aggregates"]) == {"reinforce", "td3"}
    assert set(summary["holm_adjusted"]) == {
        "reinforce vs td3 on pendulum",
        "reinforce vs td3 on inverted_pendulum",
    }
    assert "Holm" in summary["correction"]
    report = (suite_dir / "report.md").read_text()
    assert "| reinforce |" in report and "optimality gap" in report
    assert "band is the IQM's 90% stratified bootstrap CI" in report  # the report's level, drawn
    for name in ("performance_profile.png", "sample_efficiency.png"):
        assert (suite_dir / name).stat().st_size > 1000
    for env_id in ("Pendulum-v1", "InvertedPendulum-v5"):  # each env keeps its own section
        assert (out / "suite_test" / env_id / "report.md").is_file()

    line = one_line_error(
        run_cli(["envs=[pendulum,walker3d]", *store["overrides"]], cwd=store["path"],
                module="walkers.compare")
    )  # fmt: skip
    assert "envs: 'walker3d' is not allowed: must be one of" in line
    assert len(all_runs(store["client"])) >= 8
