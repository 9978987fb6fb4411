"""``python -m walkers.evaluate``: replay a trained policy, print its return, record a video.

    python -m walkers.evaluate run_id=<id> checkpoint=best episodes=10 video=true out=<dir>
    python -m walkers.evaluate checkpoint=path/to/last.pt render=human

The replay itself is :mod:`walkers.training.checkpoint_evaluation`.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.cli import exit_on_bad_overrides, or_exit


@hydra.main(config_path=str(CONF_DIR), config_name="evaluate")
def main(cfg: DictConfig) -> None:
    from walkers.training.checkpoint_evaluation import (
        evaluate,  # torch, MLflow: after the overrides' check
    )

    result = or_exit(evaluate, cfg)
    where = (
        "held-out start states (never evaluated on by the run)"
        if result["start_states"] == "held_out"
        else "the start states of the run's own evaluations (best.pt was chosen on them)"
    )
    print(
        f"return over {result['episodes']} episodes from {where}: "
        f"{result['return_mean']:.1f} ± {result['return_std']:.1f} "
        f"(min {min(result['returns']):.1f}, max {max(result['returns']):.1f})"
    )
    for path in result["videos"]:
        print(f"video: {path}")


if __name__ == "__main__":
    exit_on_bad_overrides("evaluate")
    main()
