"""Plan a study from pilot runs: the seeds per arm a difference needs, and what they cost here.

``python -m walkers.plan`` (:mod:`walkers.plan`) forms the arms as ``walkers.compare`` does,
takes each arm's per-seed scores as the pilot, and for every arm against the baseline asks
:mod:`walkers.analysis.power` how many seeds per arm reach each target power for the smallest
difference worth detecting. The cost comes from the pilot runs themselves: their budget (env
steps) and measured throughput (``perf/sps``), so a plan made on these machines costs the study
on these machines.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from walkers.analysis.comparison_data import AlgoResult, Comparison
from walkers.analysis.power import analyse
from walkers.errors import ConfigError
from walkers.tracking.names import total_steps_of

#: Fewer pilot seeds than this in an arm give no usable estimate of its spread.
MIN_PILOT_SEEDS = 3


@dataclass
class ArmCost:
    """What one seed of an arm costs, from its pilot runs."""

    env_steps: float  # its budget
    hours: float  # one run's wall time at the pilot's measured env steps/s
    cpus: float  # cores one run used (torch_threads; 1 where unset)


@dataclass
class PairPlan:
    arm: str
    baseline: str
    difference: float  # the smallest difference worth detecting, in the score's units
    observed: float
    method: str
    why: str
    seeds: dict[float, int | None]  # target power -> seeds per arm


def arm_cost(result: AlgoResult, runs_by_id: dict) -> ArmCost:
    """Budget and time of one seed of ``result``'s arm, averaged over its pilot runs."""
    steps, hours, cpus = [], [], []
    for seed_run in result.runs:
        run = runs_by_id[seed_run.run_id]
        budget = float(total_steps_of(run) or "nan")
        sps = run.data.metrics.get("perf/sps", math.nan)
        steps.append(budget)
        hours.append(budget / sps / 3600 if sps and sps > 0 else math.nan)
        threads = run.data.params.get("torch_threads", "None")
        cpus.append(float(threads) if threads not in ("None", "null", "") else 1.0)
    return ArmCost(float(np.nanmean(steps)), float(np.nanmean(hours)), float(np.mean(cpus)))


def plan(
    comparison: Comparison,
    baseline: str | None,
    difference: float | None,
    relative: float | None,
    powers: Sequence[float],
    alpha: float,
    method: str = "auto",
) -> list[PairPlan]:
    """Seeds per arm for every arm against ``baseline`` (the first arm if None), for a
    difference of ``difference`` (score units), else ``relative`` x the baseline's |mean|, else
    the difference the pilot observed."""
    arms = {r.algo: r for r in comparison.algos}
    if difference is not None and relative is not None:
        raise ConfigError(
            f"difference={difference} and relative={relative} are both set: give one (score "
            "units, or a fraction of the baseline's mean), or neither (the observed difference)"
        )
    base = arms.get(baseline or next(iter(arms)))
    if base is None:
        raise ConfigError(f"baseline={baseline!r} is not an arm: one of {', '.join(arms)}")
    if len(arms) < 2:
        raise ConfigError(
            f"plan needs two arms to compare; the runs form one: {', '.join(arms)} "
            "(algos=[a,b] or group_by=<key>)"
        )
    for result in arms.values():
        if len(result.runs) < MIN_PILOT_SEEDS:
            raise ConfigError(
                f"arm {result.algo!r} has {len(result.runs)} pilot seed(s): a plan needs at "
                f"least {MIN_PILOT_SEEDS} per arm to estimate the spread (run seed=0,1,2)"
            )
    plans = []
    for result in arms.values():
        if result is base:
            continue
        observed = float(np.mean(result.scores) - np.mean(base.scores))
        wanted = (
            difference
            if difference is not None
            else relative * abs(float(np.mean(base.scores)))
            if relative is not None
            else observed
        )
        power = analyse(result.scores, base.scores, wanted, alpha, powers, method)
        plans.append(
            PairPlan(result.algo, base.algo, wanted, observed, power.method, power.why, power.seeds)
        )
    return plans


def cost_rows(pair: PairPlan, costs: dict[str, ArmCost], workers: Sequence[int]) -> list[list[str]]:
    """Per target power: seeds per arm, env steps, CPU-hours and wall time on N workers (both
    arms' seeds, each run one job)."""
    rows = []
    for power, seeds in pair.seeds.items():
        if seeds is None:
            rows.append([f"{power:.2f}", "> 200", "-", "-", *["-" for _ in workers]])
            continue
        arms = [costs[pair.arm], costs[pair.baseline]]
        steps = seeds * sum(c.env_steps for c in arms)
        cpu_hours = seeds * math.fsum(c.hours * c.cpus for c in arms)
        longest = max(c.hours for c in arms)
        walls = [math.ceil(2 * seeds / n) * longest for n in workers]
        rows.append(
            [
                f"{power:.2f}",
                str(seeds),
                f"{steps:,.0f}",
                f"{cpu_hours:.2f}",
                *[_hours(w) for w in walls],
            ]  # fmt: skip
        )
    return rows


def _hours(hours: float) -> str:
    return f"{hours * 60:.0f} min" if hours < 1 else f"{hours:.1f} h"
