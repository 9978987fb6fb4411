"""walkers: A/B-test deep-RL algorithms on simulated walking robots."""

import os
import textwrap
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


def config_options(group: str, column: int = 0, width: int = 100) -> str:
    """The options of config group ``group`` as they are on disk (``conf/<group>/*.yaml``;
    ``sweeps/*.yaml`` for ``sweeps``, a folder of the top level), comma-separated and wrapped to
    ``width`` columns for text that starts at ``column``: its next lines are indented to it."""
    folder = CONF_DIR / group if (CONF_DIR / group).is_dir() else CONFIG_ROOT / group
    options = ", ".join(sorted(path.stem for path in folder.glob("*.yaml"))) or "(none)"
    pad = " " * column
    wrapped = textwrap.fill(
        options,
        width,
        initial_indent=pad,
        subsequent_indent=pad,
        break_long_words=False,
        break_on_hyphens=False,
    )
    return wrapped[column:].replace("$", "$$")  # the help template is a string.Template


# ${walkers.options:GROUP,COLUMN} in conf/hydra/help/train.yaml: `python -m walkers.train --help`
# lists each group's options as they are on disk when it prints them (Hydra's $APP_CONFIG_GROUPS
# leaves out sweeps/, found through hydra.searchpath only once a config is composed).
if not OmegaConf.has_resolver("walkers.options"):
    OmegaConf.register_resolver("walkers.options", config_options)
