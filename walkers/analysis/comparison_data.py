"""The data model of a comparison: per-seed runs, arms' results, pairwise results, the whole
comparison (and its JSON form). Built by :mod:`walkers.analysis.comparison`, rendered by
:mod:`walkers.analysis.report`, read by :mod:`walkers.analysis.planning`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from walkers.analysis.arms import Arm
from walkers.analysis.power import PairPower
from walkers.metrics import normalized_score
from walkers.tracking.names import ENV_STEPS, GRADIENT_STEPS

AXIS_NAMES = {ENV_STEPS: "env steps", GRADIENT_STEPS: "gradient steps"}
#: The line printed with published reference figures.
PUBLISHED_CAVEAT = (
    "Published figures, not measured here: other code, budgets, seed counts and measures (see "
    "each source). Figures from another env version than the one measured are guides, not "
    "targets: Gymnasium's v5 MuJoCo envs changed the physics."
)


def _finite_or_none(x: float) -> float | None:
    """JSON has no inf/nan: "never reached" and "no CI" become null."""
    return float(x) if np.isfinite(x) else None


@dataclass
class SeedRun:
    """One training run as the comparison sees it."""

    run_id: str
    algo: str
    seed: str
    steps: np.ndarray
    returns: np.ndarray
    summary: dict[str, float]
    x_axis: str = ENV_STEPS
    dataset: str | None = None  # offline runs: what they learned from
    normalized_score: float | None = None  # offline runs: 0 = random policy, 100 = the expert's
    #: offline runs: (random, expert, where they come from), the returns normalized scores use
    references: tuple[float, float, str] | None = None
    behaviour_return: float | None = None  # offline runs: the mean return in the dataset
    cpu_hours: float | None = None  # the run's process CPU time (runs logged before: None)
    #: return-conditioned runs (DT): the final return at each target return, by target
    final_per_target: dict[str, float] = field(default_factory=dict)
    budget: int | None = None  # its total_steps, on its x-axis
    #: the run's id in the store it was first logged to (its own id, unless it was imported
    #: from a bundle): what a report names it by, the same in every store it travels to
    origin: str | None = None

    @property
    def named(self) -> str:
        return self.origin or self.run_id


@dataclass
class AlgoResult:
    """One arm's results. ``algo`` is the arm's name: the algorithm's when it has one
    configuration (see :mod:`walkers.analysis.arms`); ``arm`` tells its algorithm and
    configuration."""

    algo: str
    runs: list[SeedRun]
    scores: np.ndarray
    iqm: tuple[float, float, float]  # point, low, high
    auc: np.ndarray
    steps_to_threshold: np.ndarray  # inf where a seed never reached it
    arm: Arm | None = None
    #: return-conditioned arms (DT): the IQM of the final returns and its CI at each target
    #: return every seed was evaluated at, highest target first
    per_target: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    @property
    def algorithm(self) -> str:
        """The algorithm its runs trained (the ``algo`` tag)."""
        return self.arm.algo if self.arm else self.runs[0].algo

    @property
    def x_axis(self) -> str:
        return self.runs[0].x_axis

    @property
    def budget(self) -> int | None:
        return self.runs[0].budget

    @property
    def label(self) -> str:
        """The arm's name, and for an offline one the dataset it learned from."""
        return f"{self.algo} (offline, {self.dataset})" if self.x_axis != ENV_STEPS else self.algo

    @property
    def dataset(self) -> str | None:
        return self.runs[0].dataset

    @property
    def normalized_score_mean(self) -> float | None:
        """Mean final normalized score over the seeds that have one (offline runs)."""
        scores = [r.normalized_score for r in self.runs if r.normalized_score is not None]
        return float(np.mean(scores)) if scores else None

    def normalized(self, value: float | None) -> float | None:
        """``value`` (a return) as a normalized score on the arm's references (offline runs)."""
        refs = self.runs[0].references
        if refs is None or value is None or not np.isfinite(value) or refs[1] == refs[0]:
            return None
        return normalized_score(value, refs[0], refs[1])

    @property
    def normalized_iqm(self) -> tuple[float | None, float | None, float | None]:
        """The IQM of the final returns and its CI as normalized scores (an affine map of the
        returns, so the CI maps too; its ends are swapped where the reference is below the
        random score, which makes the map decreasing)."""
        point, low, high = (self.normalized(v) for v in self.iqm)
        if low is not None and high is not None and low > high:
            low, high = high, low
        return point, low, high

    @property
    def cpu_hours(self) -> tuple[float, int]:
        """The CPU-hours of the arm's runs that counted them, and how many did."""
        counted = [
            r.cpu_hours for r in self.runs if r.cpu_hours is not None and np.isfinite(r.cpu_hours)
        ]
        return math.fsum(counted), len(counted)

    def as_dict(self) -> dict:
        reached = np.isfinite(self.steps_to_threshold)
        refs = self.runs[0].references
        hours, counted = self.cpu_hours
        return {
            "algorithm": self.algorithm,
            "group": self.arm.group_values if self.arm else {},
            "differs_in": self.arm.distinct if self.arm else {},
            "seeds": len(self.runs),
            "x_axis": self.x_axis,
            "dataset": self.dataset,
            "normalized_score_mean": self.normalized_score_mean,
            "normalized_iqm": dict(zip(("point", "low", "high"), self.normalized_iqm, strict=True)),
            "references": dict(zip(("random", "expert", "source"), refs, strict=True))
            if refs
            else None,
            "behaviour_return": self.runs[0].behaviour_return,
            "behaviour_score": self.normalized(self.runs[0].behaviour_return),
            "run_ids": [r.named for r in self.runs],
            "score_mean": float(self.scores.mean()),
            "score_std": float(self.scores.std()),
            "iqm": self.iqm[0],
            "iqm_low": _finite_or_none(self.iqm[1]),
            "iqm_high": _finite_or_none(self.iqm[2]),
            "auc_mean": float(self.auc.mean()),
            "auc_std": float(self.auc.std()),
            "threshold_reached": int(reached.sum()),
            "steps_to_threshold_median": _finite_or_none(np.median(self.steps_to_threshold)),
            "cpu_hours": hours,
            "cpu_hours_runs": counted,
            "per_target": {
                target: {
                    "iqm": point,
                    "iqm_low": _finite_or_none(low),
                    "iqm_high": _finite_or_none(high),
                    "normalized_iqm": [self.normalized(v) for v in (point, low, high)],
                }
                for target, (point, low, high) in self.per_target.items()
            },
        }


@dataclass
class PairResult:
    """A vs B on one per-seed quantity: P(A > B) with its CI and a Mann-Whitney p-value."""

    a: str
    b: str
    quantity: str
    p_improvement: tuple[float, float, float]
    p_value: float
    power: PairPower | None = None  # the difference, its size, the power to see it, seeds

    def flipped(self) -> PairResult:
        """B vs A: P(B > A) = 1 - P(A > B), the interval mirrored; the p-value is symmetric."""
        p, low, high = self.p_improvement
        power = self.power.flipped() if self.power is not None else None
        return PairResult(
            self.b, self.a, self.quantity, (1 - p, 1 - high, 1 - low), self.p_value, power
        )

    def decisive(self, confidence: float) -> int:
        """+1 if A is reliably better, -1 if B is, 0 if the data can't tell."""
        _, low, high = self.p_improvement
        if not self.p_value < 1 - confidence:
            return 0
        return 1 if low > 0.5 else -1 if high < 0.5 else 0


@dataclass
class Comparison:
    env_id: str
    threshold: float
    #: x-axis -> total_steps of the runs compared on it (offline algorithms at different budgets:
    #: algorithm -> total_steps)
    budgets: dict[str, int | dict[str, int]]
    score: str
    confidence: float
    algos: list[AlgoResult]
    pairs: list[PairResult]
    grids: dict[str, np.ndarray]  # x-axis -> steps of the aligned learning curves
    left_out: list[str] = field(default_factory=list)
    group_by: list[str] = field(default_factory=list)  # the study's keys; []: by algorithm
    splits: list[str] = field(default_factory=list)  # groups of several configurations
    published: list[dict] = field(default_factory=list)  # reference figures (conf/env/*.yaml)
    references: list[dict] = field(default_factory=list)  # bundles arms came from (provenance)

    def as_dict(self) -> dict:
        return {
            "env": self.env_id,
            "threshold": self.threshold,
            "total_steps": self.budgets.get(ENV_STEPS),
            "gradient_steps": self.budgets.get(GRADIENT_STEPS),
            "score": self.score,
            "confidence": self.confidence,
            "algos": {r.algo: r.as_dict() for r in self.algos},
            "pairs": [
                {
                    "a": p.a,
                    "b": p.b,
                    "quantity": p.quantity,
                    "p_improvement": p.p_improvement[0],
                    "p_improvement_low": _finite_or_none(p.p_improvement[1]),
                    "p_improvement_high": _finite_or_none(p.p_improvement[2]),
                    "mann_whitney_p": p.p_value,
                    "verdict": p.decisive(self.confidence),
                    "power": p.power.__dict__ if p.power is not None else None,
                }
                for p in self.pairs
            ],
            "left_out": self.left_out,
            "group_by": self.group_by,
            "split": self.splits,
            "published": self.published,
            "published_caveat": PUBLISHED_CAVEAT if self.published else None,
            "references": self.references,
        }
