"""``python -m walkers.compare``: turn finished training runs into an A/B report.

    python -m walkers.compare env=walker2d algos=[reinforce,td3] tracking.experiment=ab_walker2d
    python -m walkers.compare env=pendulum tracking.experiment=sizes group_by=algo.hidden_sizes
    python -m walkers.compare envs=[pendulum,inverted_pendulum] tracking.experiment=ab_tiny
    python -m walkers.compare env=walker2d algos=[td3bc,dt] datasets=[walkers/walker2d/medium,...]

The comparison itself is :mod:`walkers.analysis.comparison`, the report
:mod:`walkers.analysis.report`.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.analysis.comparison import compare
from walkers.analysis.report import verdict
from walkers.analysis.suite_report import compare_datasets, compare_suite
from walkers.cli import exit_on_bad_overrides, group_by_as_list, or_exit


@hydra.main(config_path=str(CONF_DIR), config_name="compare")
def main(cfg: DictConfig) -> None:
    if cfg.envs or cfg.datasets:
        verdict_line, out = or_exit(compare_suite if cfg.envs else compare_datasets, cfg)
        print(verdict_line)
        print(f"suite report: {out / 'report.md'}")
        return
    comparison, out, url = or_exit(compare, cfg)
    print(verdict(comparison))
    print(f"report: {out / 'report.md'}")
    if url:
        print(f"MLflow: `make ui`, then {url}")


if __name__ == "__main__":
    sys.argv[1:] = group_by_as_list(sys.argv[1:])
    exit_on_bad_overrides("compare")
    main()
