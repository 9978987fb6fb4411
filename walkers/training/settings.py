"""The run's own settings (``total_steps``, ``eval_every``, ``seed``, ``device``...), declared once,
and a composed config checked before any work starts (and before an MLflow run exists).

Like an algorithm's hyperparameters (:mod:`walkers.agents.declarations.schemas`), each
setting is a field of :class:`RunSettings` made by ``hp(default, allowed, doc)``, and the rest
follows from it:

- the run-setting block of ``conf/train.yaml``, each value commented with its doc
  (:func:`write_train_yaml`, ``make menus``; a test holds it in step with the declaration). The
  rest of that file (the defaults list, ``pruning``, ``trial``, ``hydra``) is written by hand;
- the help of ``python -m walkers.train --help``, ``conf/hydra/help/train.yaml`` (Hydra's
  ``hydra.help``, chosen in ``conf/train.yaml``'s defaults list; :func:`write_help_yaml`, ``make
  menus``): each setting with its doc, then the config groups of that defaults list (their options
  read from disk when the help prints), examples, and last the keys walkers and its sweepers set;
- the check of a composed config (:func:`validate`): the run's settings and the env's by
  :data:`RULES`, the algorithm's hyperparameters against their one declaration
  (:mod:`walkers.agents.declarations.schemas`), then what needs several keys at once; every error
  one line naming the key, the bad value and what is allowed;
- what a run's book reads (:meth:`RunSettings.of`: the settings a run's config gives).

``allowed=None``: not checked here, as before this declaration existed: ``dataset`` and
``resume`` are checked where they are used, ``seeds_per_trial`` by the sweeper; ``save_buffer``,
``progress``, ``work_dir`` and ``job_key`` are taken as given.

    python -m walkers.training.settings [--check]
"""

from __future__ import annotations

import logging
import re
import sys
import textwrap
from dataclasses import dataclass, fields
from pathlib import Path

from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError

from walkers import PROJECT_ROOT
from walkers.agents.declarations import menus
from walkers.agents.declarations.menus import entry, yaml_value  # the algorithm menus' layout
from walkers.agents.declarations.schemas import (
    NON_NEGATIVE_INT,
    NUMBER,
    POSITIVE_INT,
    SCHEMAS,
    Allowed,
    Replay,
    hp,
    or_null,
    problems,
    schema_of,
)
from walkers.agents.sb3.arguments import SB3_CLASSES, sb3_arguments
from walkers.agents.sb3.twin import import_sb3
from walkers.errors import ConfigError
from walkers.metrics import METRIC_DIRECTIONS
from walkers.training.provenance import worker_name

OPTIMIZABLE_METRICS = tuple(METRIC_DIRECTIONS)  # every metric a sweep can optimize
DEVICES = ("auto", "cpu", "cuda")
IMPLEMENTATIONS = ("walkers", "sb3")
VECTOR_ENVS = ("auto", "sync", "async")
#: the algorithms that train seed populations: the replay-based actor-critics
REPLAY_BASED = [name for name, schema in SCHEMAS.items() if issubclass(schema, Replay)]
#: the algorithms that learn from a dataset (``dataset=``): their agent class says offline = True
OFFLINE = [name for name, schema in SCHEMAS.items() if get_class(schema.AGENT).offline]

log = logging.getLogger("walkers")


def _listed(choices) -> Allowed:
    return Allowed(lambda v: v in choices, "one of " + ", ".join(choices))


@dataclass
class RunSettings:
    """The settings of one training run (the top level of ``conf/train.yaml``), in its order."""

    seed: int = hp(
        0,
        NON_NEGATIVE_INT,
        "every random stream of the run derives from it (walkers/seeding.py): no two seeds share "
        "a start state",
    )
    impl: str = hp(
        "walkers",
        _listed(IMPLEMENTATIONS),
        f"whose implementation trains: {' | '.join(IMPLEMENTATIONS)} (Stable-Baselines3's twin of "
        f"{'/'.join(SB3_CLASSES)}; pip install -e '.[sb3]')",
    )
    population: int = hp(
        1,
        POSITIVE_INT,
        f"{'/'.join(REPLAY_BASED)}: train seeds seed..seed+K-1 together in one process (stacked "
        "networks), one MLflow run each",
    )
    vector_env: str = hp(
        "auto",
        _listed(VECTOR_ENVS),
        "how a run's several training envs step (a population's K, PPO's algo.num_envs): sync (in "
        "this process, in turn) | async (a worker process each) | auto (async for 8 or more envs "
        "on at least as many cores, else sync: measured, docs/speed.md)",
    )
    total_steps: int = hp(1_000_000, POSITIVE_INT, "environment steps to train for")
    eval_every: int = hp(5_000, POSITIVE_INT, "env steps between evaluations")
    eval_episodes: int = hp(10, POSITIVE_INT, "deterministic episodes per evaluation")
    checkpoint_every: int = hp(
        50_000, POSITIVE_INT, "env steps between checkpoints/last.pt (also written at the end)"
    )
    save_buffer: bool = hp(
        False,
        None,
        "also upload the replay buffer with last.pt (large: ~170 MB per 1M Walker2d steps); the "
        "local resume copy always has it",
    )
    dataset: str | None = hp(
        None,
        None,
        f"offline algorithms ({'/'.join(OFFLINE)}): the Minari dataset id to learn from",
    )
    resume: str | list[str] | None = hp(
        None,
        None,
        "an MLflow run id: continue that run from its last checkpoint (the local copy with its "
        "replay buffer if this machine trained it)",
    )
    device: str = hp("auto", _listed(DEVICES), " | ".join(DEVICES))
    torch_threads: int | None = hp(
        1,
        or_null(POSITIVE_INT),
        "torch intra-op threads; 1 holds up when another program takes a core (more threads "
        "then run 2-3x slower: docs/speed.md); null: all cores, shared out among parallel jobs",
    )
    video_every: int = hp(
        0,
        Allowed(NON_NEGATIVE_INT.ok, "an integer >= 0 (0: no videos)"),
        "env steps between gifs of the greedy policy logged to the run (videos/); 0: off",
    )
    divergence_patience: int = hp(
        100,
        POSITIVE_INT,
        "updates in a row with a NaN/inf loss (each skipped) before the run ends FAILED",
    )
    log_every: int = hp(1_000, POSITIVE_INT, "env steps between loss/throughput metric logs")
    progress: bool = hp(
        True, None, "show a progress bar (steps, env steps/s, latest eval return, ETA)"
    )
    optimized_metric: str = hp(
        "final/return_last10",
        _listed(OPTIMIZABLE_METRICS),
        "the value train returns (what an Optuna sweep maximizes)",
    )
    work_dir: str = hp(
        "${oc.env:WALKERS_WORK_DIR,.walkers}",
        None,
        "local scratch: checkpoints before upload, downloads",
    )
    seeds_per_trial: int = hp(
        1,
        None,
        "a sweep trial's seeds (seed, seed+1, ...): one job each (in parallel over the launcher);"
        "\nthe trial scores their mean and is pruned on the mean of their evaluations",
    )
    job_key: str | None = hp(
        None,
        None,
        "set by walkers.train in a multirun (sweep dir + job number; a study's jobs: "
        "study/trial/seed):\na job run again after its worker died finds its earlier run by it "
        "and continues it",
    )

    @classmethod
    def of(cls, config: DictConfig | dict) -> RunSettings:
        """The settings a config gives: a composed one, or a run's resolved ``config`` (a key it
        lacks: the default)."""
        if OmegaConf.is_config(config):
            config = OmegaConf.to_container(config, resolve=True)
        return cls(**{f.name: config[f.name] for f in fields(cls) if f.name in config})


#: The checked run settings as ``(key, allowed)``, in declaration order (see the module doc), then
#: the env's; an algorithm's hyperparameters are checked against theirs.
RULES: list[tuple[str, Allowed]] = [
    *((f.name, f.metadata["allowed"]) for f in fields(RunSettings) if f.metadata["allowed"]),
    ("env.max_episode_steps", or_null(POSITIVE_INT)),
    ("env.threshold", NUMBER),
    ("env.learning_starts", NON_NEGATIVE_INT),
]


# --- the check of a composed config ------------------------------------------------------------
_MISSING = object()


def _algo_values(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg.algo, resolve=True)


def is_offline(cfg: DictConfig) -> bool:
    """Whether ``cfg.algo`` learns from a dataset (its agent class says ``offline = True``)."""

    return bool(getattr(get_class(cfg.algo._target_), "offline", False))


def _check_population(cfg: DictConfig) -> None:

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
    sb3_arguments(cfg.algo.name, _algo_values(cfg))  # a setting SB3 cannot express: one line
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
            f"algorithms ({', '.join(OFFLINE)}) train on a dataset; online ones "
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


# --- conf/train.yaml's settings block and the help, written from the declaration -----------------
#: The line of ``conf/train.yaml`` after which the run settings are written, up to a blank line.
HEADING = (
    "# The run's own settings: written by `make menus` from walkers/training/settings.py "
    "(edit them there)."
)


#: What the ``algo`` group's options need to know: the offline algorithms.
OFFLINE_DOC = f"{', '.join(OFFLINE)}: offline, need dataset="


def algorithms_comment() -> str:
    """The comment of the defaults list's ``algo`` line: every declared algorithm."""
    return f"# {' | '.join(SCHEMAS)} ({OFFLINE_DOC})"


def train_yaml(text: str) -> str:
    """``text`` (``conf/train.yaml``) with the block after :data:`HEADING` written anew, and the
    defaults list's ``algo`` line commented with every declared algorithm."""
    lines = [
        line.split("#")[0] + algorithms_comment() if line.startswith("  - algo:") else line
        for line in text.split("\n")
    ]
    if HEADING not in lines:
        raise ValueError(f"conf/train.yaml has no line {HEADING!r} to write the settings after")
    start = lines.index(HEADING) + 1
    end = lines.index("", start)  # the block ends at the first blank line
    defaults = RunSettings()
    block = [
        line
        for f in fields(RunSettings)
        for line in entry(f.name, yaml_value(getattr(defaults, f.name)), f.metadata["doc"])
    ]
    return "\n".join(lines[:start] + block + lines[end:])


def write_train_yaml(conf_dir=None, check: bool = False) -> list[str]:
    """Write the run settings into ``<conf_dir>/train.yaml`` (default: the project's ``conf/``);
    with ``check``, write nothing. Returns the file when it was out of step, else nothing."""
    path = Path(conf_dir or PROJECT_ROOT / "conf") / "train.yaml"
    text = path.read_text()
    written = train_yaml(text)
    if written == text:
        return []
    if not check:
        path.write_text(written)
    return [str(path)]


#: Where :func:`write_help_yaml` writes the help of ``walkers.train``, under ``conf/``.
HELP_YAML = Path("hydra") / "help" / "train.yaml"
HELP_WIDTH = 100  # the help's lines fit a terminal this wide
HELP_COLUMN = 24  # where the docs start, after ``key=default``
#: Run settings that walkers sets itself: --help lists them last, beside the sweepers' keys.
SET_BY_WALKERS = ("job_key",)
HELP_HEADER = (
    "python -m walkers.train [-m] [key=value ...]: train one agent on one environment, logged to "
    "MLflow. Set a run setting as key=value, pick a config group's option as group=option; -m: "
    "several runs at once (seed=0,1,2), a sweep or a study."
)
HELP_FOOTER = (
    "Every key of the composed config (algo.*, env.*, ...): python -m walkers.train --cfg job "
    "[overrides]. Hydra's own flags and groups: --hydra-help. The guide: docs/getting-started.md, "
    "docs/training.md."
)
#: The help's examples: a run, a sweep, a study.
HELP_EXAMPLES = (
    ("python -m walkers.train algo=sac env=hopper seed=3 total_steps=300000", "one run"),
    ("python -m walkers.train -m sweeps=td3_walker2d", "an Optuna sweep (sweeps/)"),
    ("python -m walkers.train -m ab=tiny", "an A/B study to its verdict"),
)


def _literal(text: str) -> str:
    """``text`` as it reads in the help template: ``$`` escaped for Hydra's string.Template, then
    ``${`` for OmegaConf, which resolves the template before it (``work_dir``'s default)."""
    return text.replace("$", "$$").replace("${", "\\${")


def _item(head: str, doc: str) -> list[str]:
    """``head`` (``key=default``) and ``doc`` wrapped beside it from :data:`HELP_COLUMN`; a head
    too wide for the column gets a line of its own."""
    pad = " " * HELP_COLUMN
    text = " ".join(doc.split())  # a doc's line breaks are those of its yaml comment
    lines = textwrap.wrap(
        text, HELP_WIDTH, initial_indent=pad, subsequent_indent=pad, break_on_hyphens=False
    )
    if not lines:
        return [_literal(head)] if head else []
    if len(head) <= HELP_COLUMN - 2:
        lines[0] = head + lines[0][len(head) :]
    else:
        lines.insert(0, head)
    return [_literal(line) for line in lines]


def _comment(line: str) -> str:
    return line.split("#", 1)[1].strip() if "#" in line else ""


def help_template(train: str) -> str:
    """The template of ``python -m walkers.train --help``, from the declared run settings and
    ``train`` (the text of ``conf/train.yaml``: its defaults list's groups, ``pruning`` and
    ``trial``). A group's options are read from disk when the help prints them
    (``${walkers.options:GROUP,COLUMN}``, :func:`walkers.config_options`)."""
    defaults = RunSettings()
    lines = [
        "${hydra.help.header}",
        "== Run settings: key=default (any of them on the command line) ==",
    ]
    for f in fields(RunSettings):
        if f.name not in SET_BY_WALKERS:
            head = f"{f.name}={yaml_value(getattr(defaults, f.name))}"
            lines += _item(head, f.metadata["doc"])
    lines += ["", "== Config groups: group=default, then its options (group=option) =="]
    defaults_list = train.split("\ndefaults:\n", 1)[1].split("\n\n", 1)[0]
    for line in defaults_list.split("\n"):
        group = re.match(r"  - (\w+): (\S+)", line)  # not _self_, not an override of hydra/
        if group:
            head = f"{group[1]}={group[2]}"
            doc = OFFLINE_DOC if group[1] == "algo" else _comment(line)
            options = "${walkers.options:" + f"{group[1]},{HELP_COLUMN}" + "}"
            lines += [head.ljust(HELP_COLUMN) + options] + _item("", doc)
    lines += ["", "== Examples =="]
    width = max(len(command) for command, _ in HELP_EXAMPLES)
    lines += [f"{command.ljust(width)}  # {what}" for command, what in HELP_EXAMPLES]
    lines += ["", "== Set by walkers, its sweepers and sweeps/*.yaml (listed for reference) =="]
    for f in fields(RunSettings):
        if f.name in SET_BY_WALKERS:
            lines += _item(f"{f.name}={yaml_value(getattr(defaults, f.name))}", f.metadata["doc"])
    composed = OmegaConf.create(train)
    for key in ("pruning", "trial"):
        doc = _comment(next(line for line in train.split("\n") if line.startswith(f"{key}:")))
        keys = ", ".join(
            f"{key}.{sub}" + ("" if value is None else f"={yaml_value(value)}")
            for sub, value in composed[key].items()
        )
        lines += _item(f"{key}.*", f"{doc}: {keys}")
    lines += _item(
        "hydra.*",
        "Hydra's own settings and groups (hydra/launcher=joblib: a multirun's "
        "jobs in parallel): --hydra-help",
    )
    lines += ["", "${hydra.help.footer}"]
    return "\n".join(lines)


def _block(lines: list[str]) -> str:
    """``lines`` as a yaml block scalar's (``key: |``) indented text."""
    return "\n".join(f"  {line}".rstrip() for line in lines)


def help_yaml(train: str) -> str:
    """The text of ``conf/hydra/help/train.yaml`` (see :func:`help_template`)."""
    header, footer = (
        _literal(textwrap.fill(text, HELP_WIDTH)) for text in (HELP_HEADER, HELP_FOOTER)
    )
    return "\n".join(
        [
            "# `python -m walkers.train --help` (Hydra's hydra.help, chosen in conf/train.yaml's "
            "defaults list):",
            "# written by `make menus` from walkers/training/settings.py and conf/train.yaml "
            "(edit them there).",
            "# ${walkers.options:GROUP,COLUMN}: a group's options, read from disk as the help "
            "prints.",
            "app_name: walkers.train",
            "header: |",
            _block(header.split("\n")),
            "footer: |-",  # the template ends the line
            _block(footer.split("\n")),
            "template: |",
            _block(help_template(train).split("\n")),
            "",
        ]
    )


def write_help_yaml(conf_dir=None, check: bool = False) -> list[str]:
    """Write the help of ``walkers.train`` into ``<conf_dir>/hydra/help/train.yaml`` (default:
    the project's ``conf/``) from ``<conf_dir>/train.yaml``; with ``check``, write nothing.
    Returns the file when it was out of step, else nothing."""
    conf = Path(conf_dir or PROJECT_ROOT / "conf")
    path = conf / HELP_YAML
    written = help_yaml((conf / "train.yaml").read_text())
    if path.is_file() and path.read_text() == written:
        return []
    if not check:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(written)
    return [str(path)]


def write_all(conf_dir=None, check: bool = False) -> list[str]:
    """``make menus``: conf/train.yaml's run settings, then the help written from it."""
    return write_train_yaml(conf_dir, check) + write_help_yaml(conf_dir, check)


if __name__ == "__main__":  # make menus
    sys.exit(menus.main(write_all, "walkers/training/settings.py", sys.argv[1:]))
