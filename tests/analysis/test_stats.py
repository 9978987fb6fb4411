"""The A/B statistics against values worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from walkers.analysis import stats


def test_iqm_is_the_mean_of_the_middle_half():
    assert stats.iqm(np.arange(1, 9)) == pytest.approx(4.5)  # mean of 3, 4, 5, 6
    assert stats.iqm([0, 1, 2, 3, 4, 5, 6, 1000]) == pytest.approx(3.5)  # the outlier is cut


def test_probability_of_improvement_counts_pairs_and_half_ties():
    # 1 beats {0}; 2 beats {0} and ties {2, 2}; 3 beats all three: (1 + 2 + 3) / 9
    assert stats.probability_of_improvement([1, 2, 3], [0, 2, 2]) == pytest.approx(6 / 9)
    assert stats.probability_of_improvement([0, 2, 2], [1, 2, 3]) == pytest.approx(3 / 9)
    u = sps.mannwhitneyu([1, 2, 3], [0, 2, 2]).statistic
    assert stats.probability_of_improvement([1, 2, 3], [0, 2, 2]) == pytest.approx(u / 9)


def test_fully_separated_groups():
    a, b = [10, 11, 12, 13, 14], [1, 2, 3, 4, 5]
    assert stats.poi_ci(a, b) == (1.0, 1.0, 1.0)
    # exact two-sided Mann-Whitney p for 5 vs 5 fully separated: 2 / C(10, 5)
    assert stats.mann_whitney_p(a, b) == pytest.approx(2 / math.comb(10, 5))


def test_tied_seeds_never_get_a_p_below_the_exact_tests_smallest():
    """Seeds tied at a capped return (InvertedPendulum's 1000): the normal approximation gave
    0.044 for 3 against 4, where no ordering of 7 seeds gives less than 2/35 = 0.057."""
    p = stats.mann_whitney_p([1000, 1000, 1000], [1, 2, 3, 4])
    assert p == pytest.approx(2 / math.comb(7, 3))
    assert stats.mann_whitney_p([1000, 1000, 2], [1, 2, 3, 4]) > 2 / math.comb(7, 3)


def test_the_better_side_is_where_the_seeds_rank_not_where_the_mean_is():
    a, b = list(range(50, 60)), [*range(40, 49), 900]  # B's mean is 75 above, 9 of 10 below A
    assert stats.a_ranks_higher(a, b) and not stats.a_ranks_higher(b, a)
    assert np.mean(b) > np.mean(a)


def test_overlapping_groups_have_a_ci_around_one_half():
    p, low, high = stats.poi_ci([1, 3, 5, 7], [2, 4, 6, 8])
    assert p == pytest.approx(6 / 16)
    assert low < 0.5 < high


def test_iqm_ci_resamples_seeds_within_each_task():
    # Pooled IQM = mean(3, 4, 10, 11) = 7. Every stratified replicate keeps four scores from each
    # task, so its IQM lies in [(1+1+10+10)/4, (4+4+13+13)/4]; a pooled bootstrap would not.
    point, low, high = stats.iqm_ci([[1, 2, 3, 4], [10, 11, 12, 13]], n_resamples=2000)
    assert point == pytest.approx(7.0)
    assert 5.5 <= low < point < high <= 8.5


def test_intervals_need_two_seeds():
    assert math.isnan(stats.iqm_ci([[3.0]])[1])
    assert math.isnan(stats.poi_ci([1.0], [2.0, 3.0])[1])


def test_mean_band():
    curves = np.array([[0.0, 1.0, 2.0], [2.0, 3.0, 4.0], [1.0, 2.0, 9.0]])
    mean, low, high = stats.mean_band(curves)
    np.testing.assert_allclose(mean, [1.0, 2.0, 5.0])
    assert np.all(low <= mean) and np.all(mean <= high)
    assert np.all(low >= curves.min(axis=0)) and np.all(high <= curves.max(axis=0))
    one_seed = stats.mean_band(curves[:1])
    for part in one_seed:
        np.testing.assert_allclose(part, curves[0])


def test_run_summary():
    summary = stats.run_summary([100, 200, 300], [-5.0, 1.0, 3.0], threshold=1.0)
    assert summary == {
        "final/return_mean": 3.0,
        "final/return_last10": pytest.approx(-1 / 3),
        "final/auc": pytest.approx(-1 / 3),
        "final/steps_to_threshold": 200.0,
    }
    assert stats.run_summary([100], [0.0], threshold=1.0)["final/steps_to_threshold"] == math.inf
