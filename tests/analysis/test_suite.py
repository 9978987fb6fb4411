"""The suite report: rliable's aggregates checked against numbers computed by hand, and a real
report over tiny runs on two envs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import all_runs, one_line_error, run_cli
from walkers.analysis import suite


def test_the_aggregates_match_their_definitions_by_hand():
    x = np.array([10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0])
    # IQM: the mean of the middle half (30, 40, 50, 60); optimality gap: mean shortfall below 100
    assert suite.iqm(x) == pytest.approx(45.0)
    assert suite.optimality_gap(x) == pytest.approx(np.mean(100 - x))
    assert suite.optimality_gap(np.array([120.0, 80.0])) == pytest.approx(10.0)
    cis = suite.aggregate_cis({"a": x[:4], "b": x[4:]}, n_resamples=500)
    assert cis["mean"][0] == pytest.approx(45.0) and cis["median"][0] == pytest.approx(45.0)
    for point, low, high in cis.values():
        assert low <= point <= high


#: A fixture of normalized scores (runs x envs) and what rliable 1.2.0 itself computed on it
#: (installed apart, with pandas < 3: `metrics.aggregate_*`, `probability_of_improvement`, and
#: `library.get_interval_estimates` with 20,000 stratified bootstrap draws for the CIs). Its
#: median is rliable's: over envs of each env's mean score (A: 83.2; the pooled median is 77).
RLIABLE_FIXTURE = {
    "A": np.array([[12.0, 85.0, 140.0], [-4.0, 91.0, 60.0], [30.0, 77.0, 105.0],
                   [8.0, 99.0, 131.0], [21.0, 64.0, 88.0]]),
    "B": np.array([[2.0, 40.0, 95.0], [10.0, 55.0, 72.0], [-8.0, 61.0, 110.0],
                   [5.0, 38.0, 83.0], [15.0, 47.0, 66.0]]),
}  # fmt: skip
RLIABLE_SAYS = {
    "A": {
        "mean": (67.13333333333334, 57.2, 76.6),
        "median": (83.2, 71.8, 93.0),
        "IQM": (68.33333333333333, 58.44444444444444, 79.22222222222223),
        "optimality gap": (37.93333333333333, 31.66666666666667, 44.80166666666652),
    },
    "B": {
        "mean": (46.06666666666666, 40.4, 51.86666666666667),
        "median": (48.2, 40.6, 55.8),
        "IQM": (44.888888888888886, 40.333333333333336, 50.78055555555532),
        "optimality gap": (54.6, 49.53333333333333, 59.733333333333334),
    },
}
RLIABLE_P_A_BETTER = (0.8, 0.6266666666666666, 0.9466666666666667)


def _per_env(matrix: np.ndarray) -> dict[str, np.ndarray]:
    return {f"env{j}": matrix[:, j] for j in range(matrix.shape[1])}


@pytest.mark.parametrize("arm", ["A", "B"])
def test_every_aggregate_is_rliable_s_own(arm):
    """Points to the last digit; CIs (another random stream) within a normalized point."""
    ours = suite.aggregate_cis(_per_env(RLIABLE_FIXTURE[arm]), n_resamples=20_000)
    for name, (point, low, high) in RLIABLE_SAYS[arm].items():
        assert ours[name][0] == pytest.approx(point, rel=1e-12), name
        assert ours[name][1] == pytest.approx(low, abs=1.0), name
        assert ours[name][2] == pytest.approx(high, abs=1.0), name


def test_probability_of_improvement_is_rliable_s_own():
    a, b = (_per_env(RLIABLE_FIXTURE[arm]) for arm in ("A", "B"))
    point, low, high = suite.average_improvement(a, b, n_resamples=5000)
    assert point == pytest.approx(RLIABLE_P_A_BETTER[0], rel=1e-12)
    assert (low, high) == pytest.approx(RLIABLE_P_A_BETTER[1:], abs=0.02)


def test_the_bootstrap_is_stratified_by_env():
    # two envs whose scores never overlap: a stratified resample keeps half the runs in each, so
    # the pooled median stays between the envs; resampling across envs would not
    per_env = {"low": np.zeros(6), "high": np.full(6, 100.0)}
    _, low, high = suite.aggregate_cis(per_env, n_resamples=300)["mean"]
    assert low == high == 50.0


def test_probability_of_improvement_is_averaged_over_envs():
    a = {"e1": np.array([3.0, 4.0]), "e2": np.array([0.0, 1.0])}
    b = {"e1": np.array([1.0, 2.0]), "e2": np.array([0.0, 5.0])}
    # e1: A wins all 4 pairs (1.0); e2: (0>0 tie .5, 0<5, 1>0, 1<5) -> 1.5/4
    point, low, high = suite.average_improvement(a, b, n_resamples=300)
    assert point == pytest.approx((1.0 + 1.5 / 4) / 2)
    assert low <= point <= high


def test_holm_adjusts_step_down():
    adjusted = suite.holm({"a": 0.01, "b": 0.04, "c": 0.03})
    assert adjusted == pytest.approx({"a": 0.03, "c": 0.06, "b": 0.06})


def test_performance_profile_counts_runs_above_tau_each_task_weighed_alike():
    taus = np.array([-1.0, 25.0, 100.0])
    profile = suite.performance_profile({"a": np.array([0.0, 50.0, 100.0])}, taus)
    assert profile.tolist() == pytest.approx([1.0, 2 / 3, 0.0])
    # 1 seed above 25 of 1 on one env, 0 of 3 on the other: 1/2, not the pooled 1/4 (rliable)
    two = {"few": np.array([30.0]), "many": np.array([0.0, 10.0, 20.0])}
    assert suite.performance_profile(two, taus).tolist() == pytest.approx([1.0, 0.5, 0.0])


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
