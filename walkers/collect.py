"""``python -m walkers.collect``: record behaviour policies as a Minari dataset.

    python -m walkers.collect run_id=<id> episodes=100 dataset=walkers/walker2d/td3-expert
    python -m walkers.collect run_id=random env=pendulum episodes=50 dataset=walkers/pendulum/random

The recording itself is :mod:`walkers.training.dataset_recording`.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.cli import exit_on_bad_overrides, or_exit


@hydra.main(config_path=str(CONF_DIR), config_name="collect")
def main(cfg: DictConfig) -> None:
    from walkers.training.dataset_recording import (
        collect,  # torch, MLflow: after the overrides' check
    )

    stats = or_exit(collect, cfg)
    print(
        f"dataset {stats['dataset']}: {stats['episodes']} episodes, {stats['steps']} steps, "
        f"return {stats['return_mean']:.1f} ± {stats['return_std']:.1f} "
        f"(min {stats['return_min']:.1f}, median {stats['return_median']:.1f}, "
        f"max {stats['return_max']:.1f}); random policy {stats['random_return']:.1f}; "
        f"digest {stats['digest']}"
    )
    print(f"stored in {stats['path']}")
    if "mlflow_url" in stats:
        print(f"MLflow: `make ui`, then {stats['mlflow_url']}")


if __name__ == "__main__":
    exit_on_bad_overrides("collect")
    main()
