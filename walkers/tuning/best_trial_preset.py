"""``python -m walkers.preset study=NAME``: a study's best trial as a ``conf/experiment`` preset.

(The key is ``study``, not ``sweep``: Hydra reads ``sweep=...`` as a choice in the ``sweep/``
config group.)

    python -m walkers.preset study=td3_walker2d
    python -m walkers.train experiment=td3_walker2d_tuned seed=3

The preset selects the sweep's algorithm and env and pins the best trial's sampled values; the
per-trial budget of the sweep is left out, so the preset trains with the full default budget.
"""

from __future__ import annotations

from pathlib import Path

import optuna
from hydra import compose
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from walkers import PROJECT_ROOT
from walkers.errors import ConfigError
from walkers.tuning.studies import absolute_storage, redacted

EXPERIMENT_DIR = PROJECT_ROOT / "conf" / "experiment"


def best_trial(storage: str, study_name: str) -> optuna.trial.FrozenTrial:
    try:
        study = optuna.load_study(study_name=study_name, storage=storage)
    except KeyError:
        raise ConfigError(
            f"study {study_name!r} is not in {redacted(storage)}; run the sweep first "
            f"(python -m walkers.train -m sweeps={study_name})"
        ) from None
    try:
        return study.best_trial
    except ValueError:
        raise ConfigError(
            f"study {study_name!r} in {redacted(storage)} has no completed trial"
        ) from None


def preset_yaml(name: str, sweep_cfg: DictConfig, trial, storage: str) -> str:
    """The preset: the sweep's algo/env choices, its algo settings, the trial's sampled values."""
    choices = sweep_cfg.hydra.runtime.choices
    study, sweep = sweep_cfg.hydra.sweeper.study_name, choices.sweeps
    lines = [
        "# @package _global_",
        f"# Tuned by the Optuna study {study!r} (sweeps/{sweep}.yaml, "
        f"storage {redacted(storage)}):",
        f"# best trial {trial.number}: {sweep_cfg.optimized_metric} = {trial.value}.",
        f"#   python -m walkers.train experiment={name}",
        "defaults:",
        f"  - override /algo: {choices.algo}",
        f"  - override /env: {choices.env}",
        "",
    ]
    algo = OmegaConf.to_container(sweep_cfg.algo, resolve=False)  # the sweep's fixed settings too
    values = OmegaConf.create(
        {"algo": {k: v for k, v in algo.items() if k not in ("_target_", "name")}}
    )
    parser = OverridesParser.create()
    for dotted, value in trial.params.items():  # "algo.lr" -> algo: {lr: ...}
        # read each value as the trial's job read its override ("[256,256]" is a list)
        parsed = parser.parse_override(f"{dotted}={value}").value()
        OmegaConf.update(values, dotted, parsed, force_add=True)
    return "\n".join(lines) + OmegaConf.to_yaml(values)


def write_preset(cfg: DictConfig) -> Path:
    try:
        sweep_cfg = compose("train", overrides=[f"sweeps={cfg.study}"], return_hydra_config=True)
    except Exception:
        names = sorted(p.stem for p in (PROJECT_ROOT / "sweeps").glob("*.yaml"))
        raise ConfigError(
            f"study={cfg.study!r} is not a file in sweeps/: one of {', '.join(names)}"
        ) from None
    storage = absolute_storage(cfg.storage or sweep_cfg.hydra.sweeper.storage)
    study = sweep_cfg.hydra.sweeper.study_name
    trial = best_trial(storage, study)
    name = cfg.name or f"{cfg.study}_tuned"
    path = Path(cfg.dir or EXPERIMENT_DIR) / f"{name}.yaml"
    if path.exists() and not cfg.force:
        raise ConfigError(f"{path} exists; pass force=true to overwrite it or name=<other name>")
    path.write_text(preset_yaml(name, sweep_cfg, trial, storage))
    return path
