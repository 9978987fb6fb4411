"""Command-line overrides checked before Hydra runs: its composition errors as one line, exit 2.

Hydra reports an unknown option (``algo=foo``) or key (``totl_steps=5``) as a multi-line message
with the config search path and exits 1. Every walkers command composes its config here first
and turns those errors into the project's form: ``error: <key>=<value> ...`` on one line, exit 2.
"""

from __future__ import annotations

import os
import sys

from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException
from omegaconf import OmegaConf
from omegaconf.errors import InterpolationKeyError, InterpolationResolutionError

from walkers import CONF_DIR as _CONF_DIR
from walkers.errors import CheckpointError, ConfigError, did_you_mean
from walkers.secrets import has_password, redacted, refuse_password

CONF_DIR = str(_CONF_DIR)
#: Sweep values Hydra can enumerate (a,b,c / range()); Optuna's interval() etc. are the sweeper's.
_ENUMERABLE = ("ChoiceSweep", "RangeSweep")


#: Hydra flags followed by a value that is not an override.
_FLAGS_WITH_VALUE = {
    "--cfg",
    "-c",
    "--package",
    "-p",
    "--config-path",
    "-cp",
    "--config-name",
    "-cn",
    "--config-dir",
    "-cd",
    "--experimental-rerun",
}


def overrides_of(args: list[str]) -> list[str]:
    """The overrides among a command line's arguments (flags and their values dropped)."""
    overrides, skip = [], False
    for arg in args:
        if skip:
            skip = False
        elif arg in _FLAGS_WITH_VALUE:
            skip = True
        elif not arg.startswith("-"):
            overrides.append(arg)
    return overrides


def _single_values(args: list[str]) -> list[list[str]]:
    """Override lists to compose: multirun sweeps become one list per swept value."""
    overrides = overrides_of(args)
    parsed = OverridesParser.create().parse_overrides(overrides)
    base = []
    for override in parsed:
        if override.is_sweep_override():
            if type(override.value()).__name__ not in _ENUMERABLE:
                continue  # an Optuna search space: checked by the sweeper
            values = list(override.sweep_string_iterator())
            base.append((override, values))
        else:
            base.append((override, None))
    first = [o.input_line if v is None else f"{o.get_key_element()}={v[0]}" for o, v in base]
    combos = [first]
    for i, (override, values) in enumerate(base):
        for value in (values or [])[1:]:
            combos.append(first[:i] + [f"{override.get_key_element()}={value}"] + first[i + 1 :])
    return combos


def one_line_hydra_error(error: Exception, overrides: list[str], keys=()) -> str:
    """A Hydra composition error as one line naming the bad override, the closest allowed
    names and what is allowed (``keys``: the config's keys, for an unknown one)."""
    if isinstance(error, MissingConfigException) and error.missing_cfg_file:
        group, _, name = error.missing_cfg_file.rpartition("/")
        options = error.options or []
        return (
            f"{group}={name!r} is not allowed: {did_you_mean(name, options)}"
            f"must be one of {', '.join(options)}"
        )
    key = unknown_key(error)
    if key is not None:
        given = next((o for o in overrides if o.split("=", 1)[0].lstrip("+~") == key), key)
        return (
            f"{given}: there is no key {key!r} in the config; {did_you_mean(key, keys)}"
            "(see `--cfg job` for the keys; prefix + to add a new one)"
        )
    return str(error).splitlines()[0]


def unknown_key(error: Exception) -> str | None:
    """The key a Hydra composition error says is not in the config, if it says that."""
    text = str(error)
    return text.split("'")[1] if text.startswith("Could not override '") else None


def config_keys(config_name: str, overrides: list[str]) -> list[str]:
    """Every dotted key of ``config_name`` composed with ``overrides`` (none if they fail)."""
    try:
        cfg = OmegaConf.to_container(compose(config_name=config_name, overrides=overrides))
    except Exception:
        return []

    def walk(node, prefix):
        for k, v in node.items():
            yield f"{prefix}{k}"
            if isinstance(v, dict):
                yield from walk(v, f"{prefix}{k}.")

    return list(walk(cfg, ""))


#: Config names renamed in 0.2 (old -> new): the old ones still work for one release, with a note.
RENAMED = {
    "sweep/pruner": "pruner",  # the pruner group (conf/pruner/)
    "sweep.pruner": "pruner",  # its settings, e.g. sweep.pruner.lower
    "sweep.warmup_steps": "pruning.warmup_steps",
    "sweep.startup_trials": "pruning.startup_trials",
}


def renamed_overrides(args: list[str]) -> list[str]:
    """``args`` with renamed config keys given their new names, each noted once on stderr."""
    out = []
    for arg in args:
        prefix, key = "", arg
        while key[:1] in ("+", "~"):
            prefix, key = prefix + key[0], key[1:]
        for old, new in RENAMED.items():
            if key == old or key.startswith((f"{old}=", f"{old}.")):
                print(
                    f"note: {old} is now {new} (the old name goes in the next release)",
                    file=sys.stderr,
                )
                key = new + key[len(old) :]
                break
        out.append(prefix + key)
    return out


def exit_on_bad_overrides(config_name: str, args: list[str] | None = None, check=None) -> None:
    """Compose ``config_name`` with the command line's overrides, and ``check`` each composed
    config (a :class:`ConfigError` for a bad value); on error: one line, exit 2, before Hydra
    has created a folder or a run."""
    args = sys.argv[1:] if args is None else args
    if any(a in ("--help", "-h", "--hydra-help", "--info", "-i") for a in args):
        return
    try:
        combos = _single_values(args)
        with initialize_config_dir(config_dir=CONF_DIR):
            for overrides in combos:
                cfg = compose(config_name=config_name, overrides=overrides)
                _resolvable(cfg)
                # before Hydra writes the overrides into .hydra/ files and its launch log
                refuse_password(
                    OmegaConf.select(cfg, "tracking.uri", throw_on_resolution_failure=False)
                )
                if check is not None:
                    check(cfg)
    except (MissingConfigException, ConfigCompositionException, OverrideParseException) as e:
        keys = []
        if (key := unknown_key(e)) is not None:  # the config's keys without the unknown one
            others = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") != key]
            with initialize_config_dir(config_dir=CONF_DIR):
                keys = config_keys(config_name, others)
        print(f"error: {one_line_hydra_error(e, args, keys)}", file=sys.stderr)
        sys.exit(2)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except InterpolationKeyError as e:
        key, reason = e.full_key, str(e).splitlines()[0]
        values = [o.split("=", 1)[1] for o in overrides_of(args) if o.startswith(f"{key}=")]
        value = values[0] if values else None
        if has_password(value):  # a store URL's password stays out of the line
            value = redacted(value)
        given = key if value is None else f"{key}={value}"
        print(f"error: {given}: {reason}", file=sys.stderr)
        sys.exit(2)


def _resolvable(cfg) -> None:
    """Raise InterpolationKeyError for a ``${...}`` that names no key of ``cfg``. What a
    resolver reads where the job runs (``${oc.env:...}``: a cluster node's environment) is the
    job's to check, not this process's."""
    try:
        OmegaConf.to_container(cfg, resolve=True)
    except InterpolationKeyError:
        raise
    except InterpolationResolutionError:
        pass


def or_exit(command, cfg):
    """``command(cfg)``; bad input (a :class:`ConfigError` or :class:`CheckpointError`) becomes
    ``error: ...`` on one line of stderr and exit 2."""
    try:
        return command(cfg)
    except (ConfigError, CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def group_by_as_list(args: list[str]) -> list[str]:
    """``group_by=a,b`` -> ``group_by=[a,b]``: Hydra reads a bare comma list as a sweep, which
    means nothing to a report; quoted or bracketed values pass as they are."""
    return [
        f"group_by=[{arg.partition('=')[2]}]"
        if arg.startswith("group_by=") and "," in arg and arg[9:10] not in ("[", "'", '"')
        else arg
        for arg in args
    ]


def jobs_at_once(launcher) -> int | None:
    """How many jobs Hydra's ``launcher`` config runs at once: the basic launcher one, joblib
    its ``n_jobs`` (-1: every core); None where the launcher does not say (a Ray cluster's
    size is the cluster's)."""
    if "BasicLauncher" in launcher.get("_target_", ""):
        return 1
    n_jobs = launcher.get("n_jobs")
    if n_jobs is None:
        return None
    return (os.cpu_count() or 1) if n_jobs < 0 else n_jobs
