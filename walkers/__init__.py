"""walkers: A/B-test deep-RL algorithms on simulated walking robots."""

import os
from pathlib import Path

from omegaconf import OmegaConf

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering unless the user asks otherwise

_PACKAGE = Path(__file__).resolve().parent
#: The repository root of a checkout (an editable install); git provenance is read from here.
PROJECT_ROOT = _PACKAGE.parent
#: Where ``conf/`` and ``sweeps/`` are: the repository's top level in a checkout; inside the
#: package once installed from a wheel (``pip install .`` ships both as package data).
CONFIG_ROOT = PROJECT_ROOT if (PROJECT_ROOT / "conf" / "train.yaml").is_file() else _PACKAGE
CONF_DIR = CONFIG_ROOT / "conf"
SWEEPS_DIR = CONFIG_ROOT / "sweeps"

# ${walkers.root:} in configs: lets conf/train.yaml put sweeps/ on Hydra's search path whatever
# the working directory, in a checkout and in an installed package alike.
if not OmegaConf.has_resolver("walkers.root"):
    OmegaConf.register_resolver("walkers.root", lambda: str(CONFIG_ROOT))
