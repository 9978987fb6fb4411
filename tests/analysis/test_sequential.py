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


def test_the_better_arm_is_the_one_the_rank_test_found_not_the_one_with_the_higher_mean():
    """Nine of B's ten seeds below every seed of A, and one far above them all: the rank test
    rejects because A ranks higher, so the answer is A, whatever B's mean (89 points above)."""
    from walkers.analysis.sequential import decide_look

    design = Design(alpha=0.05, questions=1, looks=(10,), delta=0.0)
    a, b = list(range(10, 20)), [*range(9), 1000]
    result = decide_look(a, b, design, 0)
    assert result.decision == A_BETTER and result.p_value < 0.002
    assert result.difference == pytest.approx(-89.1)
    assert decide_look(b, a, design, 0).decision == "B better"


def test_the_power_a_study_reports_when_not_settled_is_at_most_what_its_design_had():
    """A question not settled at the maximum reports a power for the smallest difference: a lower
    bound (its last look alone), never more than the design's own, measured by running 300
    studies of it on arms exactly that difference apart."""
    from walkers.analysis.sequential import reached_power

    spec = spec_for(arms=2, envs=1, seeds=(5, 15, 2), alpha=0.05, delta=10)
    rng = np.random.default_rng(5)
    n = 300
    outcomes = [simulate(spec, {"arm0": 60, "arm1": 50}, "normal", 10.0, rng) for _ in range(n)]
    found = sum(o.decisions["arm0 vs arm1 on env0"] == A_BETTER for o in outcomes)
    design = Design.of(alpha=0.05, questions=1, seeds_min=5, seeds_max=15, per_round=2, delta=10)
    unit = (lambda x: (x - x.mean()) / x.std(ddof=1))(np.arange(15.0))  # sd exactly 1
    bound = reached_power(60 + 10 * unit, 50 + 10 * unit, design)
    # the design's power is above the bound: the bound is below the rate's 99.9% upper limit
    assert bound <= float(sps.beta.ppf(0.999, found + 1, n - found)), (bound, found / n)
    assert 0.2 < bound < 0.6


def test_tied_seeds_never_decide_below_the_exact_tests_smallest_p():
    """Four seeds of A tied at a capped return against four distinct seeds of B: the normal
    approximation's p (0.021) is below what any exact ordering of 4 against 4 can give
    (2/70 = 0.029); the look does not decide where the design said it could not."""
    from walkers.analysis.sequential import _two_sided_p, smallest_p

    p = _two_sided_p(np.full(4, 1000.0), np.array([1.0, 2.0, 3.0, 4.0]))
    assert p == pytest.approx(smallest_p(4, two_sided=True))
