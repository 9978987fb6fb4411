"""``python -m walkers.plan``: how many seeds per arm a study needs, and what it costs here.

    python -m walkers.plan env=pendulum algos=[reinforce,td3] tracking.experiment=ab_pendulum
    python -m walkers.plan env=walker2d tracking.experiment=sizes group_by=algo.hidden_sizes \
        relative=0.1

The pilot is the runs a report would compare (:mod:`walkers.analysis.comparison`); the power
analysis is :mod:`walkers.analysis.power`, the plan and its cost :mod:`walkers.analysis.planning`.
"""

from __future__ import annotations

import sys

import hydra
import numpy as np
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.analysis.comparison import build_comparison
from walkers.analysis.planning import arm_cost, cost_rows, plan
from walkers.analysis.power import CLOSED_FORM, RESAMPLING
from walkers.cli import exit_on_bad_overrides, group_by_as_list, or_exit
from walkers.errors import ConfigError

METHODS = {"auto": "auto", "closed": CLOSED_FORM, "resampling": RESAMPLING}


def make_plan(cfg: DictConfig) -> str:
    """The plan as text (what the command prints)."""
    if cfg.method not in METHODS:
        raise ConfigError(f"method={cfg.method!r} is not allowed: one of {', '.join(METHODS)}")
    powers = list(cfg.powers)
    if not powers or not all(isinstance(p, float) and 0 < p < 1 for p in powers):
        raise ConfigError(f"powers={powers} is not allowed: numbers between 0 and 1")
    comparison, client = build_comparison(cfg)
    alpha = 1 - cfg.confidence
    plans = plan(comparison, cfg.baseline, cfg.difference, cfg.relative, powers, alpha,
                 METHODS[cfg.method])  # fmt: skip
    runs = {r.run_id: client.get_run(r.run_id) for a in comparison.algos for r in a.runs}
    costs = {a.algo: arm_cost(a, runs) for a in comparison.algos}
    lines = [
        f"Pilot on {comparison.env_id}, score {comparison.score}: "
        + "; ".join(
            f"{a.algo} {len(a.runs)} seeds, mean {np.mean(a.scores):.4g} ± "
            f"{np.std(a.scores, ddof=1):.3g}, {costs[a.algo].env_steps:,.0f} env steps and "
            f"{costs[a.algo].hours * 60:.1f} min a run"
            for a in comparison.algos
        )
        + f". Test: two-sided Mann-Whitney U at alpha {alpha:.2g}, as in the report."
    ]
    for p in plans:
        given = (
            "the difference the pilot observed"
            if cfg.difference is None and cfg.relative is None
            else f"relative={cfg.relative} of the baseline's mean"
            if cfg.relative is not None
            else f"difference={cfg.difference}"
        )
        lines += [
            "",
            f"{p.arm} vs {p.baseline}: to detect a difference of {p.difference:+.4g} ({given}; "
            f"observed {p.observed:+.4g})",
            f"method: {p.method}: {p.why}",
            "",
            "| power | seeds per arm | env steps | CPU-hours | "
            + " | ".join(f"wall on {n} worker{'s' * (n > 1)}" for n in cfg.workers)
            + " |",
            "|---" * (4 + len(cfg.workers)) + "|",
        ]
        lines += ["| " + " | ".join(row) + " |" for row in cost_rows(p, costs, cfg.workers)]
    return "\n".join(lines)


@hydra.main(config_path=str(CONF_DIR), config_name="plan")
def main(cfg: DictConfig) -> None:
    print(or_exit(make_plan, cfg))


if __name__ == "__main__":
    sys.argv[1:] = group_by_as_list(sys.argv[1:])
    exit_on_bad_overrides("plan")
    main()
