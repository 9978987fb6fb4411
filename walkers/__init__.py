"""walkers: A/B-test deep-RL algorithms on simulated walking robots."""

import os
from pathlib import Path

from omegaconf import OmegaConf

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering unless the user asks otherwise

#: The repository root (where conf/ and sweeps/ live).
PROJECT_ROOT = Path(__file__).resolve().parent.parent

# ${walkers.root:} in configs: lets conf/train.yaml put the top-level sweeps/ on Hydra's search
# path whatever the working directory.
if not OmegaConf.has_resolver("walkers.root"):
    OmegaConf.register_resolver("walkers.root", lambda: str(PROJECT_ROOT))
