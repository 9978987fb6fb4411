"""``python -m walkers.ingest``: a bundle's runs into a store (``import`` is Python's keyword).

    python -m walkers.ingest bundle=results/tiny/bundle
    python -m walkers.ingest bundle=gpu_box_study tracking.uri=postgresql+psycopg://...

Checked whole before anything is written; the same bundle twice adds nothing, and a later bundle
of the same runs replaces the copies of those that went on since (KILLED then, FINISHED now) but
were not trained on here (:mod:`walkers.tracking.bundles`).
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from walkers import CONF_DIR
from walkers.cli import exit_on_bad_overrides, or_exit
from walkers.tracking import bundles
from walkers.tracking.client import connect, ui_url


def ingest(cfg: DictConfig) -> bundles.Imported:
    client = connect(cfg.tracking.uri)
    return bundles.import_bundle(client, Path(cfg.bundle), cfg.into)


@hydra.main(config_path=str(CONF_DIR), config_name="ingest")
def main(cfg: DictConfig) -> None:
    done = or_exit(ingest, cfg)
    replacing = f", {done.updated} of them later versions of earlier copies" * bool(done.updated)
    print(
        f"imported {len(done.added)} runs from {cfg.bundle}{replacing} ({done.present} already "
        f"there); open them: `make ui`, then {ui_url(done.experiment_id)}"
    )


if __name__ == "__main__":
    exit_on_bad_overrides("ingest")
    main()
