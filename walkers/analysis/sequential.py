"""Seeds in rounds, stopping when the answer is known: the A/B study's group-sequential test.

A study asks questions: each pair of arms on each env, and, over a suite of envs, each pair on
the aggregate (the mean normalized score over the envs, per seed). After every round of seeds
each open question gets one of four answers, by a rule fixed before the study starts:

- **A better / B better**: the report's own test, a two-sided Mann-Whitney U (exact without
  ties), rejects "no difference" at this look's level;
- **equal**: two one-sided Mann-Whitney tests (TOST, on the samples shifted by the smallest
  difference worth detecting ``delta``) both reject "the difference is at least delta";
- **continue**: neither, and seeds are left; at the last look the answer is **not settled**,
  with the power the study reached for ``delta``.

The family-wise error rate stays at or below ``alpha``: Bonferroni over the questions (each
gets ``alpha / questions``), and within a question an alpha-spending function over the looks,
Lan and DeMets' Pocock type ``alpha(t) = alpha_q * ln(1 + (e - 1) t)`` with ``t`` the fraction
of the maximum seeds seen; look ``k`` tests at the increment ``alpha(t_k) - alpha(t_k-1)``, so
by the union bound the chance of any false "better" or false "equal" is at most ``alpha_q`` per
question whatever the returns' distribution (the rank tests are exact). Pocock's shape spends
early, so an obvious difference stops at the first look (O'Brien-Fleming's would need dozens of
seeds before its first look could reject anything). ``tests/analysis/test_sequential.py`` and
``benchmarks/bench_sequential.py`` check the error rate by simulation (normal, bimodal,
heavy-tailed returns; several pairs and envs at once) and measure the seeds saved against a
fixed-n design of the same power.

AdaStop (Mathieu et al. 2023) was read first and not used: in ``adastop`` 0.1.3 the statistic
is the absolute difference of means but its permutation distribution the signed one, so its
level is about twice the asked one (measured here: 0.11 at alpha = 0.05 with one look, 0.15
with four).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from walkers.analysis.power import RANK_TEST_EFFICIENCY, welch_power
from walkers.analysis.stats import a_ranks_higher, mann_whitney_p

A_BETTER, B_BETTER, EQUAL, CONTINUE, NOT_SETTLED = (
    "A better",
    "B better",
    "equal",
    "continue",
    "not settled",
)
DECIDED = (A_BETTER, B_BETTER, EQUAL)


@dataclass(frozen=True)
class Design:
    """The test fixed before a study starts: its looks, levels and smallest difference.

    ``looks``: seeds per arm at each look (the minimum, one more round at a time, the maximum);
    ``questions``: how many questions share ``alpha`` (Bonferroni); ``delta``: the smallest
    difference worth detecting, in the units of the scores the questions are asked on.
    """

    alpha: float
    questions: int
    looks: tuple[int, ...]
    delta: float

    @classmethod
    def of(
        cls,
        alpha: float,
        questions: int,
        seeds_min: int,
        seeds_max: int,
        per_round: int,
        delta: float,
    ) -> Design:
        looks = tuple(range(seeds_min, seeds_max, per_round)) + (seeds_max,)
        return cls(alpha, questions, looks, delta)

    @property
    def alpha_per_question(self) -> float:
        return self.alpha / self.questions

    def spent(self, k: int) -> float:
        """Alpha spent by one question through look ``k`` (0-based; -1: none)."""
        if k < 0:
            return 0.0
        t = self.looks[k] / self.looks[-1]
        return self.alpha_per_question * math.log(1 + (math.e - 1) * t)

    def level(self, k: int) -> float:
        """The level look ``k`` tests at: what it adds to the alpha spent."""
        return self.spent(k) - self.spent(k - 1)

    def first_look_can_decide(self) -> bool:
        """Whether complete separation at the first look reaches the first look's level."""
        return 0 in self.deciding_looks()

    def deciding_looks(self) -> tuple[int, ...]:
        """The looks (0-based) at which "better" can be answered at all: complete separation of
        the arms' seeds (the smallest p the exact rank test can give) reaches the look's level.
        At any other look the answer is "continue" whatever the returns."""
        return tuple(
            k for k, n in enumerate(self.looks) if smallest_p(n, two_sided=True) <= self.level(k)
        )

    def equal_looks(self) -> tuple[int, ...]:
        """The looks at which "equal" can be answered at all: both one-sided tests of the TOST
        reach the look's level at their smallest p (none when ``delta`` is 0: not asked)."""
        if self.delta <= 0:
            return ()
        return tuple(
            k for k, n in enumerate(self.looks) if smallest_p(n, two_sided=False) <= self.level(k)
        )


def fewest_seeds(level: float, *, two_sided: bool = True) -> int:
    """The fewest seeds per arm whose smallest p reaches ``level``."""
    n = 1
    while smallest_p(n, two_sided=two_sided) > level:
        n += 1
    return n


def looks_table(design: Design) -> str:
    """Each look of a design as a markdown table: its seeds, its level, and whether "better" and
    "equal" can be answered there at all (with the fewest seeds that could, at that level)."""
    better, equal = set(design.deciding_looks()), set(design.equal_looks())
    rows = [
        "| look | seeds per arm | level | smallest p | can answer 'better' | can answer 'equal' "
        "| fewest seeds per arm that could |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, n in enumerate(design.looks):
        rows.append(
            f"| {k + 1} | {n} | {design.level(k):.3g} | {smallest_p(n, two_sided=True):.3g} "
            f"| {'yes' if k in better else 'no'} "
            f"| {'yes' if k in equal else 'no' if design.delta > 0 else 'not asked'} "
            f"| {fewest_seeds(design.level(k))} |"
        )
    return "\n".join(rows) + "\n"


def equal_line(design: Design) -> str:
    """Whether the design can ever answer "equal" (the TOST reaching a look's level)."""
    if design.delta <= 0:
        return "'equal' is not asked (smallest_difference is 0)"
    looks = design.equal_looks()
    if not looks:
        return (
            f"'equal' can never be answered: at {design.looks[-1]} seeds per arm the "
            "equivalence test cannot reach its level (raise hydra.sweeper.seeds.max)"
        )
    return f"'equal' can be answered from {design.looks[looks[0]]} seeds per arm"


def smallest_p(n: int, *, two_sided: bool) -> float:
    """The smallest p the exact Mann-Whitney U test gives for ``n`` against ``n`` seeds: complete
    separation, one ordering of the ``C(2n, n)`` equally likely ones (two of them two-sided)."""
    return min(1.0, (2 if two_sided else 1) / math.comb(2 * n, n))


@dataclass(frozen=True)
class Answer:
    """A question's answer: the decision, the look it came at and what it saw."""

    decision: str
    look: int  # 0-based index into Design.looks
    seeds: int
    p_value: float  # the superiority test's at that look
    difference: float  # mean(A) - mean(B)
    power: float = math.nan  # for delta at the last look (not settled / equal at the end)

    @property
    def settled(self) -> bool:
        return self.decision in DECIDED


def _two_sided_p(a: np.ndarray, b: np.ndarray) -> float:
    return mann_whitney_p(a, b, "two-sided")


def decide_look(a: Sequence[float], b: Sequence[float], design: Design, k: int) -> Answer:
    """The answer at look ``k`` from the first ``looks[k]`` seeds of each arm."""
    n = design.looks[k]
    return _look(tuple(map(float, a[:n])), tuple(map(float, b[:n])), design, k)


@functools.lru_cache(maxsize=4096)
def _look(a_seeds: tuple[float, ...], b_seeds: tuple[float, ...], design: Design, k: int) -> Answer:
    """:func:`decide_look` of seeds as tuples, remembered: a study replays every earlier look
    each round (:func:`answer`), and its simulations (:mod:`walkers.ab.simulation`) do so
    thousands of times; a look's seeds never change once it is reached."""
    n = len(a_seeds)
    a, b = np.asarray(a_seeds), np.asarray(b_seeds)
    level = design.level(k)
    p = _two_sided_p(a, b)
    difference = float(a.mean() - b.mean())
    if p <= level:  # the side the rank test found, not the means' (one outlier seed flips those)
        return Answer(A_BETTER if a_ranks_higher(a, b) else B_BETTER, k, n, p, difference)
    if design.delta > 0:
        # TOST: "A - B <= -delta" and "A - B >= delta" both rejected
        above = mann_whitney_p(a + design.delta, b, "greater")
        below = mann_whitney_p(a - design.delta, b, "less")
        if max(above, below) <= level:
            return Answer(EQUAL, k, n, p, difference)
    if k < len(design.looks) - 1:
        return Answer(CONTINUE, k, n, p, difference)
    return Answer(NOT_SETTLED, k, n, p, difference, reached_power(a, b, design))


def reached_power(a: np.ndarray, b: np.ndarray, design: Design) -> float:
    """A lower bound on the power the study had to detect ``delta``: that of its last look
    alone, a test of this many seeds at the last look's level (closed form at the rank test's
    efficiency, the arms' observed spreads). The earlier looks add to it; a fixed test at the
    question's whole alpha would overstate it (one question, seeds 5-15 by 2, a 1-sd difference:
    0.73 that way, about 0.44 by simulating 400 studies of the design, 0.35 this way)."""
    if design.delta <= 0 or min(len(a), len(b)) < 2:
        return math.nan
    n = len(a) * RANK_TEST_EFFICIENCY
    sd_a, sd_b = float(np.std(a, ddof=1)), float(np.std(b, ddof=1))
    return welch_power(design.delta, sd_a, sd_b, n, n, design.level(len(design.looks) - 1))


def answer(a: Sequence[float], b: Sequence[float], design: Design) -> Answer:
    """Replay the looks the seeds at hand allow and return the first decision, else the state
    at the last look reached (``continue``). Deterministic: the same seeds, the same answer, so
    a resumed study needs no stored state. Each arm's scores are in seed order."""
    reached = [k for k, n in enumerate(design.looks) if n <= min(len(a), len(b))]
    if not reached:
        return Answer(CONTINUE, -1, min(len(a), len(b)), math.nan, math.nan)
    for k in reached:
        result = decide_look(a, b, design, k)
        if result.decision != CONTINUE:
            return result
    return result


def next_look_seeds(result: Answer, design: Design) -> int:
    """Seeds per arm the question needs for its next look (its current count if settled)."""
    if result.decision != CONTINUE:
        return result.seeds
    return design.looks[result.look + 1]


@dataclass
class Question:
    """One question of a study: arm A against arm B on one env (``env=None``: the aggregate)."""

    a: str
    b: str
    env: str | None
    answer: Answer = field(default=None)

    @property
    def name(self) -> str:
        return f"{self.a} vs {self.b} on {self.env or 'the suite (aggregate)'}"


def suite_scores(per_env: Mapping[str, Sequence[float]]) -> list[float]:
    """Per seed, the mean normalized score over the envs, for the seeds every env has."""
    n = min(len(v) for v in per_env.values())
    return [float(np.mean([per_env[env][i] for env in per_env])) for i in range(n)]
