"""The A/B study's stopping rule, checked by simulation through the study's own round logic:
the family-wise error rate stays at or below alpha for any shape of returns, an obvious
difference stops at the first look, and identical arms are never called different more often
than alpha allows. (Figures at full size: `make bench-sequential`.)"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from walkers.ab.simulation import SHAPES, simulate, spec_for
from walkers.analysis.sequential import A_BETTER, Design, answer


def consistent_with_at_most(alpha: float, errors: int, n: int) -> bool:
    """Whether ``errors`` in ``n`` simulated studies is consistent with a rate <= ``alpha``: the
    rate's one-sided 99.9% Clopper-Pearson lower bound is at or below it."""
    return errors == 0 or float(sps.beta.ppf(0.001, errors, n - errors + 1)) <= alpha


@pytest.mark.parametrize("shape", SHAPES)
def test_one_pair_keeps_the_error_rate_at_alpha(shape):
    spec = spec_for(arms=2, envs=1, seeds=(5, 11, 2), alpha=0.05, delta=10)
    rng = np.random.default_rng(0)
    n = 250
    wrong = sum(simulate(spec, {"arm0": 50, "arm1": 50}, shape, 10.0, rng).wrong for _ in range(n))
    assert consistent_with_at_most(0.05, wrong, n), wrong


@pytest.mark.parametrize("shape", SHAPES)
def test_several_pairs_and_envs_keep_the_family_wise_rate_at_alpha(shape):
    # 3 arms x 2 envs + the aggregate: 9 questions share alpha
    spec = spec_for(arms=3, envs=2, seeds=(5, 7, 2), alpha=0.05, delta=10)
    rng = np.random.default_rng(1)
    n = 60
    equal = {"arm0": 50, "arm1": 50, "arm2": 50}
    wrong = sum(simulate(spec, equal, shape, 10.0, rng).wrong for _ in range(n))
    assert consistent_with_at_most(0.05, wrong, n), wrong


def test_an_equal_answer_needs_the_difference_below_delta():
    # arms a smallest difference apart are never called equal more often than alpha
    spec = spec_for(arms=2, envs=1, seeds=(5, 11, 2), alpha=0.05, delta=10)
    rng = np.random.default_rng(2)
    n = 300
    wrong = sum(
        simulate(spec, {"arm0": 60, "arm1": 50}, "normal", 3.0, rng).wrong for _ in range(n)
    )
    assert consistent_with_at_most(0.05, wrong, n), wrong


def test_an_obvious_difference_stops_at_the_first_look():
    design = Design.of(alpha=0.05, questions=1, seeds_min=5, seeds_max=15, per_round=2, delta=10)
    rng = np.random.default_rng(3)
    result = answer(rng.normal(100, 5, 15), rng.normal(0, 5, 15), design)
    assert (result.decision, result.seeds, result.look) == (A_BETTER, 5, 0)


def test_identical_arms_use_the_seeds_they_need_and_no_more():
    spec = spec_for(arms=2, envs=1, seeds=(5, 9, 2), alpha=0.05, delta=30)
    rng = np.random.default_rng(4)
    outcomes = [simulate(spec, {"arm0": 50, "arm1": 50}, "normal", 5.0, rng) for _ in range(50)]
    # a spread well under the smallest difference: "equal", at the first look (5 seeds per arm)
    equal = [o for o in outcomes if o.decisions["arm0 vs arm1 on env0"] == "equal"]
    assert len(equal) >= 45
    assert all(o.seeds == 2 * 5 for o in equal)


def test_the_levels_spend_alpha_exactly_once():
    design = Design.of(alpha=0.05, questions=3, seeds_min=5, seeds_max=20, per_round=5, delta=1)
    assert design.looks == (5, 10, 15, 20)
    assert math.isclose(sum(design.level(k) for k in range(4)), 0.05 / 3)
    assert all(design.level(k) > 0 for k in range(4))


@pytest.mark.parametrize(
    ("questions", "seeds"), [(1, (2, 6, 1)), (3, (3, 4, 1)), (3, (5, 7, 1)), (9, (6, 20, 2))]
)
def test_the_looks_that_can_decide_are_those_where_separated_seeds_decide(questions, seeds):
    """``deciding_looks``/``equal_looks`` say exactly where the real test can answer: completely
    separated arms answer "better" there and only there, and arms within ``delta`` of each other
    answer "equal" there and only there."""
    from walkers.analysis.sequential import EQUAL, decide_look, smallest_p

    design = Design.of(0.05, questions, *seeds, 10.0)
    for k, n in enumerate(design.looks):
        low, high = np.arange(n, dtype=float), np.arange(n, dtype=float) + 1000
        separated = decide_look(high, low, design, k).decision == A_BETTER
        assert separated == (k in design.deciding_looks()), (k, n)
        alike = np.arange(n, dtype=float) * 1e-3  # interleaved, far inside delta
        equal = decide_look(alike, alike + 5e-4, design, k).decision == EQUAL
        assert equal == (k in design.equal_looks()), (k, n)
        exact = sps.mannwhitneyu(high, low, method="exact").pvalue
        assert smallest_p(n, two_sided=True) == pytest.approx(exact)
