"""``python -m walkers.plan``: how many seeds per arm a study needs, and what it costs here.

    python -m walkers.plan env=pendulum algos=[reinforce,td3] tracking.experiment=ab_pendulum
    python -m walkers.plan env=walker2d tracking.experiment=sizes group_by=algo.hidden_sizes \
        relative=0.1
    python -m walkers.plan study=locomotion        # a study file's looks: which can decide

The pilot is the runs a report would compare (:mod:`walkers.analysis.comparison`); the power
analysis is :mod:`walkers.analysis.power`, the plan and its cost :mod:`walkers.analysis.planning`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from walkers import CONF_DIR
from walkers.ab.spec import StudySpec
from walkers.analysis.comparison import build_comparison
from walkers.analysis.planning import arm_cost, cost_rows, plan
from walkers.analysis.power import CLOSED_FORM, RESAMPLING
from walkers.analysis.sequential import equal_line, looks_table
from walkers.cli import exit_on_bad_overrides, group_by_as_list, or_exit
from walkers.errors import ConfigError

STUDY_FIELDS = ("name", "arms", "envs", "seeds", "score", "alpha", "smallest_difference")
METHODS = {"auto": "auto", "closed": CLOSED_FORM, "resampling": RESAMPLING}


def make_plan(cfg: DictConfig) -> str:
    """The plan as text (what the command prints)."""
    if cfg.study is not None:
        return study_looks(str(cfg.study))
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


def study_looks(study: str) -> str:
    """A study file's design, look by look: its seeds, level, and whether "better" and "equal"
    can be answered there at all, with the fewest seeds that could (what the sweeper checks)."""
    path = Path(study) if study.endswith((".yaml", ".yml")) else CONF_DIR / "ab" / f"{study}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in (CONF_DIR / "ab").glob("*.yaml")))
        raise ConfigError(
            f"study={study!r} is not allowed: a study file (a .yaml path) or one of {known}"
        )
    declared = OmegaConf.to_container(OmegaConf.load(path)).get("hydra", {}).get("sweeper")
    if not isinstance(declared, dict):
        raise ConfigError(f"study={study!r}: {path} declares no hydra.sweeper (not a study file)")
    declared = {k: v for k, v in declared.items() if k in STUDY_FIELDS}
    spec = StudySpec.parse(**declared)
    design = spec.design()
    lines = [
        f"Study {spec.name!r}: {design.questions} questions (alpha {spec.alpha:.3g}, Bonferroni: "
        f"{design.alpha_per_question:.3g} each), looks at {', '.join(map(str, design.looks))} "
        "seeds per arm. Test: two-sided Mann-Whitney U, exact; its smallest p is complete "
        "separation of the arms' seeds.",
        "",
        looks_table(design),
    ]
    try:
        spec.checked_design()
        deciding = design.deciding_looks()
        lines.append(f"'better' can be answered from {design.looks[deciding[0]]} seeds per arm.")
    except ConfigError as e:
        lines.append(f"refused by the sweeper: {e}")
    lines.append(equal_line(design) + ".")
    return "\n".join(lines)


@hydra.main(config_path=str(CONF_DIR), config_name="plan")
def main(cfg: DictConfig) -> None:
    print(or_exit(make_plan, cfg))


if __name__ == "__main__":
    sys.argv[1:] = group_by_as_list(sys.argv[1:])
    exit_on_bad_overrides("plan")
    main()
