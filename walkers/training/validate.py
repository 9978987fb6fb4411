"""Check a composed config before any work starts (and before an MLflow run exists).

The run's settings and the env's are checked by :data:`RULES` (a dotted key and what is allowed;
the run's as declared in :mod:`walkers.training.settings`), the algorithm's hyperparameters
against their one declaration (:mod:`walkers.agents.declarations.schemas`), then what needs several
keys at once. Every error is one line naming the key, the value and what is allowed.
"""

from __future__ import annotations

import logging
import re

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError

from walkers.agents.declarations.hyperparameters import (
    NON_NEGATIVE_INT,
    NUMBER,
    POSITIVE_INT,
    Allowed,
    or_null,
    problems,
)
from walkers.agents.declarations.schemas import SCHEMAS, schema_of
from walkers.agents.sb3.arguments import NotExpressible, sb3_arguments
from walkers.agents.sb3.twin import import_sb3
from walkers.errors import ConfigError
from walkers.training import settings
from walkers.training.provenance import worker_name

#: The run's own settings as declared (:mod:`walkers.training.settings`), then the env's; an
#: algorithm's hyperparameters are checked against theirs
#: (:mod:`walkers.agents.declarations.schemas`).
RULES: list[tuple[str, Allowed]] = [
    *settings.RULES,
    ("env.max_episode_steps", or_null(POSITIVE_INT)),
    ("env.threshold", NUMBER),
    ("env.learning_starts", NON_NEGATIVE_INT),
]

_MISSING = object()

log = logging.getLogger("walkers")


def _algo_values(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg.algo, resolve=True)


def is_offline(cfg: DictConfig) -> bool:
    """Whether ``cfg.algo`` learns from a dataset (its agent class says ``offline = True``)."""
    from hydra.utils import get_class

    return bool(getattr(get_class(cfg.algo._target_), "offline", False))


def _check_population(cfg: DictConfig) -> None:
    from hydra.utils import get_class

    k = cfg.get("population", 1)
    if k == 1:
        return
    if not get_class(cfg.algo._target_).trains_populations:  # declared by the class
        able = [n for n, s in SCHEMAS.items() if get_class(s.AGENT).trains_populations]
        offline = " (an offline run trains one seed: use a multirun over seeds)"
        raise ConfigError(
            f"population={k} is not allowed with algo={cfg.algo.name}: "
            f"only {', '.join(able)} train seed populations{offline if is_offline(cfg) else ''}"
        )
    for key, unsupported in (("video_every", cfg.video_every), ("a sweep", cfg.trial.id)):
        if unsupported:
            raise ConfigError(
                f"population={k} is not allowed with {key}: run the population without it "
                "(videos: walkers.evaluate on a member's run)"
            )


def _check_implementation(cfg: DictConfig) -> None:
    """``impl=sb3``: an algorithm with an SB3 twin, settings SB3 can express, SB3 installed."""
    if cfg.get("impl", "walkers") != "sb3":
        return
    try:
        sb3_arguments(cfg.algo.name, _algo_values(cfg))
    except NotExpressible as e:
        raise ConfigError(str(e)) from None
    if cfg.population > 1:
        raise ConfigError(
            f"population={cfg.population} is not allowed with impl=sb3: SB3 trains one seed "
            "per process (use a multirun over seeds)"
        )
    import_sb3()


def _check_capture(cfg: DictConfig) -> None:
    """``algo.capture`` holds the whole update in CUDA graphs; ``algo.compile`` compiles the
    losses alone: one or the other."""
    if OmegaConf.select(cfg, "algo.capture") is True and OmegaConf.select(cfg, "algo.compile"):
        raise ConfigError(
            "algo.capture=true is not allowed with algo.compile=true: capture holds the whole "
            "update as CUDA graphs, compile only its losses; choose one"
        )


def _check_dataset(cfg: DictConfig) -> None:
    dataset = cfg.get("dataset")
    if is_offline(cfg) and not dataset:
        raise ConfigError(
            f"dataset={dataset!r} is not allowed: algo={cfg.algo.name} learns offline and needs "
            "dataset=<Minari dataset id> (record one with `python -m walkers.collect`)"
        )
    if not is_offline(cfg) and dataset:
        raise ConfigError(
            f"dataset={dataset!r} is not allowed with algo={cfg.algo.name}: only offline "
            f"algorithms ({', '.join(settings.OFFLINE)}) train on a dataset; online ones "
            "collect their own experience"
        )


def _check_vector_envs(cfg: DictConfig) -> None:
    """With ``algo.num_envs`` envs stepped together the count moves ``num_envs`` at a time: the
    budget and the checkpoints fall where every env has stepped (a checkpoint between them
    would hold a step count the agent is past)."""
    n = num_envs(cfg)
    if n == 1 or cfg.get("impl", "walkers") != "walkers":
        return
    for key in ("total_steps", "checkpoint_every"):
        check(key, cfg[key], cfg[key] % n == 0, f"a multiple of algo.num_envs ({n})")


def num_envs(cfg: DictConfig) -> int:
    """The envs the run steps together (``algo.num_envs``; 1 for an algorithm without it)."""
    return OmegaConf.select(cfg, "algo.num_envs", default=1)


def check(key: str, value, ok: bool, allowed: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r} is not allowed: must be {allowed}")


def validate(cfg: DictConfig, warn: bool = True) -> None:
    """Raise :class:`ConfigError` naming the first bad key, its value and what is allowed (and
    ``warn`` of a setting that is allowed but likely a mistake)."""
    for key, allowed in RULES:
        value = OmegaConf.select(cfg, key, default=_MISSING)
        if value is _MISSING:
            continue
        if OmegaConf.is_config(value):
            value = OmegaConf.to_container(value, resolve=True)
        check(key, value, allowed.ok(value), allowed.text)
    schema = schema_of(cfg.algo.get("_target_"))  # what will be built, whatever its name
    if schema is not None and (problem := problems(schema, _algo_values(cfg))):
        raise ConfigError(problem)
    check(
        "eval_every",
        cfg.eval_every,
        cfg.eval_every <= cfg.total_steps,
        f"at most total_steps ({cfg.total_steps})",
    )
    _check_implementation(cfg)
    _check_capture(cfg)
    _check_dataset(cfg)
    _check_population(cfg)
    _check_vector_envs(cfg)
    if cfg.device == "cuda":
        import torch

        check(
            "device",
            "cuda",
            torch.cuda.is_available(),
            "auto or cpu on this machine (torch sees no CUDA device)",
        )
    if warn:
        warn_short_warmup(cfg)


def check_command(cfg: DictConfig) -> None:
    """What is checked of a command before its config can be read: ``resume=`` holds a run id
    (or several), and every environment variable the config reads is set."""
    check_resume_given(cfg.resume)
    check_environment(cfg)


def check_resume_given(resume) -> None:
    """``resume=`` with nothing after it (``resume=$RUN_ID`` with the variable unset) is a
    mistake, never a request for a fresh run."""
    empty = resume is not None and (
        (isinstance(resume, str) and not resume.strip())
        or (OmegaConf.is_list(resume) and len(resume) == 0)
    )
    if empty:
        raise ConfigError(
            f"resume={resume!r} is empty: pass the MLflow run id to continue (resume=<run id>, "
            "or resume=[<id>,<id>] for a population), or leave resume out to start a new run"
        )


def check_dataset_env(cfg: DictConfig, data) -> None:
    """An offline run's dataset was recorded on the run's env."""
    if data.env_id is not None and data.env_id != cfg.env.id:
        raise ConfigError(
            f"dataset={data.id!r} was recorded on {data.env_id}, not on env.id={cfg.env.id!r}: "
            f"pass the env it was recorded on"
        )


def warn_short_warmup(cfg: DictConfig) -> None:
    """A learning-rate warm-up longer than the run never reaches ``algo.lr`` (algo=dt)."""
    warmup = OmegaConf.select(cfg, "algo.warmup_steps")
    if warmup and warmup > cfg.total_steps:
        log.warning(
            "algo.warmup_steps=%d is more than total_steps=%d: the learning rate ends at %.0f%% "
            "of algo.lr=%g; lower algo.warmup_steps (e.g. to total_steps / 10)",
            warmup,
            cfg.total_steps,
            100 * cfg.total_steps / warmup,
            cfg.algo.lr,
        )


def check_environment(cfg: DictConfig) -> None:
    """Every ``${oc.env:NAME}`` the config reads is set where this job runs: otherwise one line
    naming the variable and the machine (a Ray worker has its node's environment as it was at
    ``ray start``: a variable exported afterwards never reaches it)."""
    try:
        OmegaConf.to_container(cfg, resolve=True)
    except InterpolationResolutionError as e:
        found = re.search(r"Environment variable '([^']+)' not found", str(e))
        if found is None:
            raise
        raise ConfigError(
            f"{found.group(1)} is not set on {worker_name()}, where this job runs: export it "
            "there (on a Ray cluster: before `ray start` on that machine)"
        ) from None
