"""How many seeds? Statistical power of an A/B study of two arms (Colas, Sigaud and Oudeyer 2018).

A pilot study (a few seeds per arm) estimates each arm's spread; a power calculation then says
how likely a study of ``n`` seeds per arm is to detect a difference ``delta`` at level
``alpha``, and how many seeds a study needs to detect it with a given power.

Two estimates, and the output always says which one it used:

- **closed form** (normal theory): Welch's t test, whose power is a noncentral t tail
  (:func:`welch_power`), at the seeds the report's rank test is worth on normal data (3/pi of
  them). Right when returns are roughly normal;
- **resampling** (:func:`simulated_power`): studies of ``n`` seeds per arm drawn from the pilot's
  own empirical distributions (each arm's pilot returns, centred, shifted to the hypothesized
  means), each decided by the report's own test (two-sided Mann-Whitney U); the power is the
  fraction that conclude. Right when RL returns are skewed or bimodal, as they often are.

:func:`choose_method` takes the closed form only where a Shapiro-Wilk test finds no departure
from normality in either arm (and the pilot is big enough to tell); otherwise resampling. The
report's rank test also has a floor: with very few seeds no outcome reaches ``alpha`` at all
(3 vs 3 seeds: the smallest two-sided p is 0.1), which :func:`min_seeds_for_rank_test` gives.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as sps

CLOSED_FORM, RESAMPLING = "closed form (Welch t, noncentral t)", "resampling (Mann-Whitney U)"
#: A pilot smaller than this cannot tell normal from not: resampling is used.
MIN_SEEDS_FOR_NORMALITY = 5
#: Studies simulated per candidate number of seeds.
SIMULATIONS = 2000
#: The most seeds per arm a plan considers.
MAX_SEEDS = 200
#: Mann-Whitney U's efficiency relative to the t test on normal data.
RANK_TEST_EFFICIENCY = 3 / math.pi


def hedges_g(a: Sequence[float], b: Sequence[float]) -> float:
    """Standardized difference of means (A - B) / pooled SD, with Hedges' small-sample factor."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n_a, n_b = len(a), len(b)
    if n_a < 2 or n_b < 2:
        return math.nan
    pooled = math.sqrt(((n_a - 1) * a.var(ddof=1) + (n_b - 1) * b.var(ddof=1)) / (n_a + n_b - 2))
    if pooled == 0:
        return math.nan if a.mean() == b.mean() else math.copysign(math.inf, a.mean() - b.mean())
    correction = 1 - 3 / (4 * (n_a + n_b) - 9)
    return float((a.mean() - b.mean()) / pooled * correction)


def welch_power(
    delta: float, sd_a: float, sd_b: float, n_a: float, n_b: float, alpha: float = 0.05
) -> float:
    """Power of the two-sided Welch t test to detect a difference of means ``delta``."""
    se = math.sqrt(sd_a**2 / n_a + sd_b**2 / n_b)
    if se == 0:
        return 1.0 if delta != 0 else alpha
    va, vb = sd_a**2 / n_a, sd_b**2 / n_b
    df = (va + vb) ** 2 / (va**2 / (n_a - 1) + vb**2 / (n_b - 1))
    critical = sps.t.ppf(1 - alpha / 2, df)
    ncp = abs(delta) / se  # symmetric: P(T > c) at +ncp and at -ncp (SciPy's nct.cdf of the
    # far tail turns NaN from ncp ~ 10, which made a large difference's power NaN)
    return float(sps.nct.sf(critical, df, ncp) + sps.nct.sf(critical, df, -ncp))


def min_seeds_for_rank_test(alpha: float = 0.05) -> int:
    """The fewest seeds per arm with which a two-sided Mann-Whitney U test can reach ``alpha``
    (complete separation of the two arms gives its smallest p-value)."""
    for n in range(2, MAX_SEEDS):
        if sps.mannwhitneyu(np.arange(n), np.arange(n) + n).pvalue < alpha:
            return n
    return MAX_SEEDS


def simulated_power(
    a: Sequence[float],
    b: Sequence[float],
    delta: float,
    n: int,
    alpha: float = 0.05,
    simulations: int = SIMULATIONS,
    seed: int = 0,
) -> float:
    """Power of the report's test for studies of ``n`` seeds per arm, resampled from the pilot.

    Each arm's pilot returns are centred; a simulated arm A draws ``n`` of A's residuals plus
    B's mean + ``delta``, arm B ``n`` of B's residuals plus B's mean. The fraction of
    simulated studies whose two-sided Mann-Whitney p-value is below ``alpha`` is the power.
    """
    rng = np.random.default_rng(seed)
    a, b = np.asarray(a, float), np.asarray(b, float)
    res_a, res_b = a - a.mean(), b - b.mean()
    sim_a = rng.choice(res_a, size=(simulations, n)) + b.mean() + delta
    sim_b = rng.choice(res_b, size=(simulations, n)) + b.mean()
    p = sps.mannwhitneyu(sim_a, sim_b, alternative="two-sided", axis=1).pvalue
    return float(np.mean(p < alpha))


def choose_method(a: Sequence[float], b: Sequence[float]) -> tuple[str, str]:
    """``(method, why)``: the closed form where both pilots look normal, else resampling."""
    if min(len(a), len(b)) < MIN_SEEDS_FOR_NORMALITY:
        return RESAMPLING, (
            f"fewer than {MIN_SEEDS_FOR_NORMALITY} pilot seeds in an arm cannot show returns "
            "are normal"
        )
    for name, x in (("A", a), ("B", b)):
        if np.ptp(x) > 0 and sps.shapiro(x).pvalue < 0.1:
            return RESAMPLING, f"arm {name}'s pilot returns depart from normal (Shapiro-Wilk)"
    return CLOSED_FORM, "both arms' pilot returns look normal (Shapiro-Wilk p >= 0.1)"


@dataclass
class Power:
    """What a power analysis says about one pair of arms."""

    method: str
    why: str
    power: float  # of a study with the pilot's seeds, for ``delta``
    seeds: dict[float, int | None]  # target power -> seeds per arm (None: more than MAX_SEEDS)


def power_of(
    a: Sequence[float],
    b: Sequence[float],
    delta: float,
    n: int,
    alpha: float,
    method: str,
) -> float:
    """Power of a study of ``n`` seeds per arm to detect ``delta``, by ``method``."""
    if method == CLOSED_FORM:
        if n < min_seeds_for_rank_test(alpha):  # the report's test cannot conclude at all
            return 0.0
        # The report's rank test on normal data does as well as a t test on 3/pi of the seeds
        # (its asymptotic relative efficiency, Noether 1955): the t test's power at that size.
        effective = n * RANK_TEST_EFFICIENCY
        return welch_power(delta, np.std(a, ddof=1), np.std(b, ddof=1), effective, effective, alpha)
    return simulated_power(a, b, delta, n, alpha)


def seeds_needed(
    a: Sequence[float], b: Sequence[float], delta: float, power: float, alpha: float, method: str
) -> int | None:
    """The fewest seeds per arm whose study reaches ``power`` for ``delta`` (None: none up to
    :data:`MAX_SEEDS`). Power grows with ``n``: a doubling search, then bisection."""

    def enough(n: int) -> bool:
        return power_of(a, b, delta, n, alpha, method) >= power

    low = min_seeds_for_rank_test(alpha)
    if enough(low):
        return low
    high = low
    while not enough(high):
        if high >= MAX_SEEDS:
            return None
        low, high = high, min(2 * high, MAX_SEEDS)
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (low, middle) if enough(middle) else (middle, high)
    return high


def analyse(
    a: Sequence[float],
    b: Sequence[float],
    delta: float,
    alpha: float = 0.05,
    targets: Sequence[float] = (0.8,),
    method: str = "auto",
) -> Power:
    """Power of the pilot-sized study for ``delta``, and the seeds each target power needs."""
    if method == "auto":
        method, why = choose_method(a, b)
    else:
        why = "asked for"
    n = min(len(a), len(b))
    return Power(
        method=method,
        why=why,
        power=power_of(a, b, delta, n, alpha, method),
        seeds={t: seeds_needed(a, b, delta, t, alpha, method) for t in targets},
    )


@dataclass
class PairPower:
    """Power in a verdict: the observed difference of means (A - B), its standardized size, the
    power the study had to detect it and the seeds per arm that would detect it with
    :data:`TARGET` power; the same for the smallest difference worth detecting."""

    difference: float
    effect_size: float
    method: str
    power: float
    seeds: int | None
    smallest: float
    power_for_smallest: float
    seeds_for_smallest: int | None

    def flipped(self) -> PairPower:
        return PairPower(**{**self.__dict__, "difference": -self.difference,
                            "effect_size": -self.effect_size})  # fmt: skip

    def precise(self) -> bool:
        """A null result says "equal within ``smallest``", not "too few seeds": the study
        would have detected a difference of ``smallest`` with :data:`TARGET` power."""
        return self.power_for_smallest >= TARGET


#: The power a study should have (Cohen's convention).
TARGET = 0.8


def pair_power(
    a: Sequence[float], b: Sequence[float], alpha: float, smallest: float
) -> PairPower | None:
    """:class:`PairPower` of arms with per-seed scores ``a`` and ``b`` (None where a score is
    not finite or an arm has fewer than 2 seeds: no spread to plan with)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if min(len(a), len(b)) < 2 or not (np.isfinite(a).all() and np.isfinite(b).all()):
        return None
    observed = float(a.mean() - b.mean())
    at_observed = analyse(a, b, observed, alpha, (TARGET,))
    at_smallest = analyse(a, b, smallest, alpha, (TARGET,), method=at_observed.method)
    return PairPower(
        difference=observed,
        effect_size=hedges_g(a, b),
        method=at_observed.method,
        power=at_observed.power,
        seeds=at_observed.seeds[TARGET],
        smallest=smallest,
        power_for_smallest=at_smallest.power,
        seeds_for_smallest=at_smallest.seeds[TARGET],
    )
