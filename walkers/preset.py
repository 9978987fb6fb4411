"""``python -m walkers.preset``: the best trial of an Optuna study -> conf/experiment/<name>.yaml.

    python -m walkers.preset study=td3_walker2d
    python -m walkers.train experiment=td3_walker2d_tuned    # then train with it

The export itself is :mod:`walkers.tuning.best_trial_preset`.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.cli import exit_on_bad_overrides, or_exit
from walkers.tuning.best_trial_preset import write_preset


@hydra.main(config_path=str(CONF_DIR), config_name="preset")
def main(cfg: DictConfig) -> None:
    path = or_exit(write_preset, cfg)
    print(f"wrote {path}")
    print(f"train with: python -m walkers.train experiment={path.stem}")


if __name__ == "__main__":
    exit_on_bad_overrides("preset")
    main()
