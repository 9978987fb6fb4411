"""The run's own settings (``total_steps``, ``eval_every``, ``seed``, ``device``...), declared once.

Like an algorithm's hyperparameters (:mod:`walkers.agents.declarations.hyperparameters`), each
setting is a field of :class:`RunSettings` made by ``hp(default, allowed, doc)``, and the rest
follows from it:

- the run-setting block of ``conf/train.yaml``, each value commented with its doc
  (:func:`write_train_yaml`, ``make menus``; a test holds it in step with the declaration). The
  rest of that file (the defaults list, ``pruning``, ``trial``, ``hydra``) is written by hand;
- the check of a composed config (:data:`RULES`, run by ``walkers.training.validate``): a
  one-line error naming the key, the bad value and what is allowed;
- what a run's book reads (:meth:`RunSettings.of`: the settings a composed config gives).

``allowed=None``: not checked here, as before this declaration existed: ``dataset`` and
``resume`` are checked where they are used, ``seeds_per_trial`` by the sweeper; ``save_buffer``,
``progress``, ``work_dir`` and ``job_key`` are taken as given.

    python -m walkers.training.settings [--check]
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, fields
from pathlib import Path

from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from walkers import PROJECT_ROOT
from walkers.agents.declarations import menus
from walkers.agents.declarations.hyperparameters import (
    NON_NEGATIVE_INT,
    POSITIVE_INT,
    Allowed,
    hp,
    or_null,
)
from walkers.agents.declarations.menus import entry, yaml_value  # the algorithm menus' layout
from walkers.agents.declarations.schemas import SCHEMAS, Replay
from walkers.agents.sb3.arguments import SB3_CLASSES
from walkers.metrics import METRIC_DIRECTIONS

OPTIMIZABLE_METRICS = tuple(METRIC_DIRECTIONS)  # every metric a sweep can optimize
DEVICES = ("auto", "cpu", "cuda")
IMPLEMENTATIONS = ("walkers", "sb3")
VECTOR_ENVS = ("auto", "sync", "async")
#: the algorithms that train seed populations: the replay-based actor-critics
REPLAY_BASED = [name for name, schema in SCHEMAS.items() if issubclass(schema, Replay)]
#: the algorithms that learn from a dataset (``dataset=``): their agent class says offline = True
OFFLINE = [name for name, schema in SCHEMAS.items() if get_class(schema.AGENT).offline]


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
        None,
        or_null(POSITIVE_INT),
        "torch intra-op threads; null: all cores, shared out among parallel sweep jobs",
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
    def of(cls, cfg: DictConfig) -> RunSettings:
        """The settings a composed config gives (resolved; a key it lacks: the default)."""
        return cls(**{f.name: _resolved(cfg, f.name) for f in fields(cls) if f.name in cfg})


def _resolved(cfg: DictConfig, key: str):
    """``cfg``'s value at ``key`` as plain Python (a list or dict, not a config node)."""
    value = OmegaConf.select(cfg, key)
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


#: The checked run settings as ``(key, allowed)``, in declaration order (see the module doc).
RULES: list[tuple[str, Allowed]] = [
    (f.name, f.metadata["allowed"]) for f in fields(RunSettings) if f.metadata["allowed"]
]

#: The line of ``conf/train.yaml`` after which the run settings are written, up to a blank line.
HEADING = (
    "# The run's own settings: written by `make menus` from walkers/training/settings.py "
    "(edit them there)."
)


def algorithms_comment() -> str:
    """The comment of the defaults list's ``algo`` line: every declared algorithm."""
    offline = ", ".join(OFFLINE)
    return f"# {' | '.join(SCHEMAS)} ({offline}: offline, need dataset=)"


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


if __name__ == "__main__":  # make menus
    sys.exit(menus.main(write_train_yaml, "walkers/training/settings.py", sys.argv[1:]))
