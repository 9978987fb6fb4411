"""How many seeds: the power analysis checked by simulation, and walkers.plan on real runs.

Monte Carlo tolerances: with S simulated studies a rate's standard error is at most
sqrt(0.25 / S); the checks allow three of them (S = 4000: 0.024) on top of any stated bias.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sps

from tests.conftest import TINY, compose_cfg, one_line_error, run_cli
from walkers.analysis import power
from walkers.errors import ConfigError
from walkers.plan import make_plan
from walkers.train import train

ALPHA = 0.05
STUDIES = 4000
MC_TOLERANCE = 3 * np.sqrt(0.25 / STUDIES)


def rejection_rate(draw_a, draw_b, n: int, seed: int = 1) -> float:
    """How often the report's test (two-sided Mann-Whitney U) concludes, over simulated
    studies of ``n`` seeds per arm drawn by ``draw_x(rng, shape)``."""
    rng = np.random.default_rng(seed)
    a, b = draw_a(rng, (STUDIES, n)), draw_b(rng, (STUDIES, n))
    return float(np.mean(sps.mannwhitneyu(a, b, axis=1).pvalue < ALPHA))


@pytest.mark.parametrize("n,delta", [(5, 1.0), (10, 1.0), (20, 0.5), (10, 0.0)])
def test_the_closed_form_matches_monte_carlo_on_normal_samples(n, delta):
    rng = np.random.default_rng(0)
    a, b = rng.normal(delta, 1, (20000, n)), rng.normal(0, 1, (20000, n))
    simulated = np.mean(sps.ttest_ind(a, b, equal_var=False, axis=1).pvalue < ALPHA)
    # the noncentral t with Welch's df is itself an approximation: within 0.03 from 5 seeds on
    assert power.welch_power(delta, 1, 1, n, n, ALPHA) == pytest.approx(simulated, abs=0.03)


def test_a_closed_form_plan_reaches_its_power_with_the_report_s_test():
    rng = np.random.default_rng(2)
    pilot_a, pilot_b = rng.normal(1.0, 1.0, 30), rng.normal(0.0, 1.0, 30)
    plan = power.analyse(pilot_a, pilot_b, delta=1.0, targets=(0.8,), method=power.CLOSED_FORM)
    n = plan.seeds[0.8]
    assert 15 <= n <= 25  # a t test needs 17 seeds per arm for d = 1 at 0.8; the rank test more

    def normal(mean):
        return lambda rng, shape: rng.normal(mean, 1.0, shape)

    achieved = rejection_rate(normal(1.0), normal(0.0), n)
    assert achieved >= 0.8 - MC_TOLERANCE, (n, achieved)
    assert rejection_rate(normal(1.0), normal(0.0), n - 3) < 0.8  # and it asks for no more


def bimodal(success_rate: float, good: float = 3000.0, bad: float = 300.0):
    """RL-like returns: a seed either learns (around ``good``) or fails (around ``bad``)."""

    def draw(rng, shape):
        learned = rng.random(shape) < success_rate
        return np.where(learned, rng.normal(good, 150, shape), rng.normal(bad, 60, shape))

    return draw


def test_a_resampled_plan_on_bimodal_returns_reaches_its_power():
    rng = np.random.default_rng(3)
    pilot_a, pilot_b = bimodal(0.8)(rng, 10), bimodal(0.3)(rng, 10)
    method, why = power.choose_method(pilot_a, pilot_b)
    assert method == power.RESAMPLING, why  # not normal: the closed form would mislead
    delta = float(pilot_a.mean() - pilot_b.mean())
    plan = power.analyse(pilot_a, pilot_b, delta, targets=(0.8,))
    n = plan.seeds[0.8]
    assert n is not None and plan.method == power.RESAMPLING

    def pilot_of(pilot):  # the pilot's own distribution, as the plan assumed
        return lambda rng, shape: rng.choice(pilot, size=shape)

    achieved = rejection_rate(pilot_of(pilot_a), pilot_of(pilot_b), n, seed=7)
    assert achieved >= 0.8 - MC_TOLERANCE, (n, achieved)


@pytest.mark.parametrize(
    "draw", [bimodal(0.5), lambda rng, shape: rng.lognormal(7, 1, shape)], ids=["bimodal", "skewed"]
)
@pytest.mark.parametrize("n", [5, 10])
def test_two_identical_arms_are_called_different_at_most_alpha_of_the_time(draw, n):
    # the report also needs P(A > B)'s interval to exclude 0.5: a verdict is rarer still
    assert rejection_rate(draw, draw, n) <= ALPHA + MC_TOLERANCE


def test_a_large_difference_has_a_power_and_fewer_seeds_for_larger_differences():
    """SciPy's noncentral t turned NaN in the far tail from a noncentrality of about 10: a
    difference four times the smallest one had power NaN, and the seeds a plan asked for jumped
    about (12 for a difference of 2, 8 for 12, 11 for 29)."""
    a = np.arange(100.0, 105.0)
    big = power.pair_power(a, a - 20, 0.05, 10.4)
    assert big.power == pytest.approx(1.0) and big.power_for_smallest > 0.99
    needed = [power.seeds_needed(a, a, d, 0.8, 0.05, power.CLOSED_FORM) for d in (2, 6, 12, 29)]
    assert needed == sorted(needed, reverse=True) and needed[-1] == needed[-2]
    assert all(n is not None for n in needed)


def test_too_few_seeds_can_never_conclude():
    assert power.min_seeds_for_rank_test(0.05) == 4  # 3 vs 3: the smallest p is 0.1
    assert power.power_of([1, 2, 3], [4, 5, 6], 5.0, 3, 0.05, power.CLOSED_FORM) == 0.0


@pytest.fixture(scope="module")
def pilot(tmp_path_factory, _empty_store_file):
    """A real pilot in a real store: REINFORCE and TD3 x 3 seeds, DDPG x 1, all tiny."""
    from tests.conftest import new_store

    store = new_store(tmp_path_factory.mktemp("pilot"), _empty_store_file)
    small = ["env=pendulum", *TINY, "algo.hidden_sizes=[16,16]", *store["overrides"]]
    for algo, seeds in (("reinforce", 3), ("td3", 3), ("ddpg", 1)):
        extra = ["algo.learning_starts=100"] if algo != "reinforce" else []
        for seed in range(seeds):
            train(compose_cfg([f"algo={algo}", f"seed={seed}", *small, *extra]))
    return store


def plan_cli(store, *args):
    return run_cli(
        ["env=pendulum", f"tracking.uri={store['uri']}", "tracking.experiment=walkers",
         f"work_dir={store['path'] / 'work'}", *args],
        cwd=store["path"],
        module="walkers.plan",
    )  # fmt: skip


def test_plan_prints_seeds_and_cost_from_a_real_pilot(pilot):
    result = plan_cli(pilot, "algos=[reinforce,td3]", "relative=0.5")
    assert result.returncode == 0, result.stderr[-3000:]
    out = result.stdout
    assert "td3 vs reinforce: to detect a difference of" in out and "relative=0.5" in out
    assert "method: " in out and ("closed form" in out or "resampling" in out)
    rows = [line for line in out.splitlines() if line.startswith("| 0.")]
    assert [row.split("|")[1].strip() for row in rows] == ["0.50", "0.80", "0.95"]
    seeds = [int(row.split("|")[2]) for row in rows if row.split("|")[2].strip().isdigit()]
    assert seeds == sorted(seeds) and all(s >= 4 for s in seeds)  # more power, more seeds
    assert "wall on 16 workers" in out and "CPU-hours" in out


@pytest.mark.parametrize(
    "args,words",
    [
        (["algos=[reinforce,td3]", "baseline=sac"], ["baseline='sac'", "reinforce, td3"]),
        (["algos=[td3,ddpg]"], ["arm 'ddpg' has 1 pilot seed(s)", "at least 3"]),
        (["algos=[reinforce,td3]", "difference=10", "relative=0.1"], ["give one"]),
        (["algos=[reinforce,td3]", "method=bayes"], ["method='bayes'", "auto, closed"]),
    ],
)
def test_plan_refuses_bad_input_in_one_line(pilot, args, words):
    cfg = compose_cfg(
        ["env=pendulum", f"tracking.uri={pilot['uri']}", "tracking.experiment=walkers", *args],
        config_name="plan",
    )
    with pytest.raises(ConfigError) as refused:
        make_plan(cfg)
    error = str(refused.value)
    assert "\n" not in error and all(word in error for word in words), error


def test_a_refused_plan_is_one_line_and_exit_2_on_the_command_line(pilot):
    error = one_line_error(plan_cli(pilot, "algos=[reinforce,td3]", "baseline=sac"))
    assert "baseline='sac'" in error and "reinforce, td3" in error, error
