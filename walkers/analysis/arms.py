"""The arms of a comparison: one arm is one configuration, run with several seeds.

A training run's MLflow params are its resolved config, flattened
(:func:`walkers.tracking.client.flatten`). Two runs belong to the same arm when those params
agree on
everything but the seed and the keys in :data:`NOT_THE_EXPERIMENT`, which cannot change what a
run learns. Runs of different configurations are never pooled: a group (an algorithm, or the
values of the ``group_by`` keys) that holds several configurations becomes several arms, named
by what sets them apart (``td3 (algo.hidden_sizes=[64, 64])``), and a note says so.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from walkers.agents.declarations.schemas import declared_since
from walkers.analysis import formatting
from walkers.errors import did_you_mean
from walkers.tracking.names import ABSENT, BUDGET_TAG, differing_keys

#: Config keys (MLflow params; a trailing "." is the whole subtree) that do not make an arm:
#: a run's results are the same for any value of these, so runs differing only here are seeds of
#: one arm. Everything else (algo.*, env.* but these, total_steps, eval_every, eval_episodes,
#: dataset...) is part of the configuration: eval_every and eval_episodes change what is measured.
NOT_THE_EXPERIMENT = (
    "seed",  # what varies between the seeds of an arm
    "resume",  # a resumed run continues the same experiment
    "population",  # a member of population=K is the same experiment as the run of its seed alone
    "progress",  # the progress bar
    "log_every",  # how often losses and throughput are logged
    "checkpoint_every",  # how often checkpoints are written
    "save_buffer",  # whether the replay buffer is uploaded with them
    "video_every",  # gifs of the greedy policy
    "tracking.",  # where the run is logged
    "work_dir",  # local scratch
    "torch_threads",  # speed only
    "vector_env",  # where the training envs step: the same envs, the same numbers
    "device",  # for CPU runs only (see arm_config): an accelerator's run stays its own arm
    "trial.",  # Optuna plumbing (study, trial id, parent run); a pruned trial is left out anyway
    "job_key",  # a multirun job's identity across attempts (walkers.train), one value per job
    "pruner.",  # when a trial may be stopped, not what it learns
    "pruning.",
    "sweep.",  # the same, as runs before the rename recorded it
    "divergence_patience",  # a run that diverges ends FAILED and is left out; others never use it
    "optimized_metric",  # the value train returns to a sweep, not what it learns
    "dataset_stats.",  # describe the dataset (named by `dataset`, part of the arm)
    "algo.compile",  # the same maths, compiled
    "env.threshold",  # only for steps-to-threshold, which the report recomputes with its own
    "env.published",  # published reference figures, shown in reports (conf/env/*.yaml)
    "env.scores.",  # the random and reference scores normalized scores are computed with
    "normalized_score.",  # an offline run's references (the same, as the run used them)
)

#: ``device`` values that mean the CPU. ``auto`` counts as CPU: the params do not record what it
#: resolved to, so an ``auto`` run on a GPU machine is not told apart from a CPU one.
CPU_DEVICES = ("cpu", "auto")

#: Keys added to the config later, with the value every run from before had: such a run is in
#: the same arm as a new run with that value (not split off as "(not set)").
LATER_KEYS = {"impl": "walkers"}  # before impl=sb3 existed, walkers trained every run


def run_params(run) -> dict[str, str]:
    """A run's params as its arm sees them: :data:`LATER_KEYS` and the algorithm's hyperparameters
    declared since the run was made (:func:`declared_later`) filled in where it lacks them."""
    params = LATER_KEYS | dict(run.data.params)
    if BUDGET_TAG in run.data.tags:  # continued to another budget than it started with
        params["total_steps"] = run.data.tags[BUDGET_TAG]
    return declared_later(params) | params


def declared_later(params: Mapping[str, str]) -> dict[str, str]:
    """The ``algo.*`` hyperparameters declared after a run with these params was made, at their
    declared defaults, as the run would have logged them: the behaviour it had before they
    existed (the rule a resume and a reference's fingerprint follow), so that it is not an arm
    of its own ("td3 (algo.capture=(not set))") beside today's runs of the same configuration."""
    target = params.get("algo._target_")
    if not target:
        return {}
    algo = {
        key.removeprefix("algo.").split(".")[0]: None for key in params if key.startswith("algo.")
    }
    added = declared_since(algo | {"_target_": target})
    return {f"algo.{key}": str(value) for key, value in added.items()}  # as flatten logs them


#: At most this many differing keys in an arm's name; the split note lists them all.
NAME_KEYS = 3


def is_not_the_experiment(key: str) -> bool:
    """Whether ``key`` is in :data:`NOT_THE_EXPERIMENT` (itself or under a listed subtree)."""
    return any(
        key.startswith(item) if item.endswith(".") else key == item for item in NOT_THE_EXPERIMENT
    )


def arm_config(params: Mapping[str, str], exclude: Iterable[str] = ()) -> dict[str, str]:
    """The part of a run's params that makes its arm: all but :data:`NOT_THE_EXPERIMENT` and
    ``exclude`` (the ``group_by`` keys, which name the group instead). ``device`` stays when it
    names an accelerator (cuda...): GPU kernels need not give the CPU's numbers."""
    excluded = set(exclude)
    return {
        key: value
        for key, value in params.items()
        if key not in excluded
        and (not is_not_the_experiment(key) or (key == "device" and value not in CPU_DEVICES))
    }


def _parsed(value: str):
    try:
        return ast.literal_eval(value)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        return value


def _is_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def natural_key(value: str) -> tuple:
    """Sort key for a param value: numbers by value, lists of numbers by their total (hidden
    sizes by total units: [64, 64] < [256] < [256, 256]) then length, anything else as text."""
    parsed = _parsed(value)
    if _is_number(parsed):
        return (0, (parsed,), value)
    if isinstance(parsed, list | tuple) and parsed and all(_is_number(x) for x in parsed):
        return (1, (sum(parsed), len(parsed), *parsed), value)
    return (2, (), value)


def assignments(keys: Sequence[str], values: Sequence[str]) -> str:
    """``k1=v1, k2=v2``."""
    return ", ".join(f"{k}={v}" for k, v in zip(keys, values, strict=True))


def describe(distinct: Mapping[str, str], limit: int = NAME_KEYS, short: bool = False) -> str:
    """``k=v, ...`` for what sets a configuration apart; ``algo.name`` comes first and makes
    ``algo._target_`` redundant (``short``: every other ``algo.*`` key too, the algorithms'
    own hyperparameters); past ``limit`` keys it says how many more there are."""
    keys = sorted(distinct, key=lambda k: (k != "algo.name", k))
    if "algo.name" in distinct:
        implied = (lambda k: k.startswith("algo.")) if short else (lambda k: k == "algo._target_")
        keys = [k for k in keys if k == "algo.name" or not implied(k)]
    shown = ", ".join(f"{k}={distinct[k]}" for k in keys[:limit])
    return shown + (f", +{len(keys) - limit} more" if len(keys) > limit else "")


def arm_name(group: str, distinct: Mapping[str, str], limit: int | None = None) -> str:
    """``group``, or ``group (k=v, ...)`` with what sets this configuration apart in its group:
    shortly (where algorithms differ, by their name alone), or with ``limit`` keys spelled out."""
    text = describe(distinct, NAME_KEYS, short=True) if limit is None else describe(distinct, limit)
    return f"{group} ({text})" if text else group


def parse_group_by(group_by) -> list[str]:
    """``group_by`` as given (null, ``"a"``, ``"a,b"`` or a list) -> a list of keys."""
    if group_by is None:
        return []
    items = [group_by] if isinstance(group_by, str) else list(group_by)
    return [key.strip() for item in items for key in str(item).split(",") if key.strip()]


def unknown_key_hint(key: str, runs_params: Sequence[Mapping[str, str]], limit: int = 12) -> str:
    """What to say about a ``group_by`` key no run has: a close match, and keys runs do have
    (first those whose values differ between the runs: the ones worth a study)."""
    known = sorted(set().union(*runs_params)) if runs_params else []
    varying = [k for k in differing_keys(runs_params) if not is_not_the_experiment(k)]
    listed = varying + [k for k in known if k not in varying]
    hint = did_you_mean(key, known)
    if not listed:
        return hint + "the runs have no params"
    more = f", ... ({len(listed) - limit} more)" if len(listed) > limit else ""
    return hint + f"keys the runs have: {', '.join(listed[:limit])}{more}"


@dataclass
class Arm:
    """One configuration and its runs (MLflow run objects, one seed each)."""

    name: str
    algo: str  # the runs' algorithm (their `algo` tag)
    group: str  # the algorithm, or the group_by assignment (k=v, ...)
    group_values: dict[str, str]  # the group_by keys and their values; {} without group_by
    config: dict[str, str]  # the arm's configuration (arm_config of its runs)
    distinct: dict[str, str] = field(default_factory=dict)  # what sets it apart in its group
    runs: list = field(default_factory=list)


def _group_of(run, group_by: Sequence[str]) -> tuple[str, ...]:
    if not group_by:
        return (run.data.tags.get("algo", "?"),)
    return tuple(run_params(run)[k] for k in group_by)


def _configs_of(runs: Sequence, exclude: Sequence[str]) -> list[tuple[dict[str, str], list]]:
    """The distinct configurations among ``runs``, each with its runs, in first-seen order."""
    by_config: dict[tuple, tuple[dict[str, str], list]] = {}
    for run in runs:
        config = arm_config(run_params(run), exclude)
        by_config.setdefault(tuple(sorted(config.items())), (config, []))[1].append(run)
    return list(by_config.values())


def split_note(group: str, arms: Sequence[Arm], keys: Sequence[str]) -> str:
    """The report's line for a group that holds several configurations."""
    listed = "; ".join(f"{a.name}: {formatting.runs(len(a.runs))}" for a in arms)
    return (
        f"{group}: {len(arms)} configurations, compared as separate arms and never pooled "
        f"(they differ in {', '.join(keys)}): {listed}"
    )


def _arms_of_group(
    group: tuple[str, ...], runs: Sequence, group_by: Sequence[str]
) -> tuple[list[Arm], str | None]:
    label = assignments(group_by, group) if group_by else group[0]
    configs = _configs_of(runs, group_by)
    keys = differing_keys([config for config, _ in configs])
    arms = []
    for config, members in configs:
        distinct = {k: config.get(k, ABSENT) for k in keys}
        arms.append(
            Arm(
                name=arm_name(label, distinct),
                algo=members[0].data.tags.get("algo", "?"),
                group=label,
                group_values=dict(zip(group_by, group, strict=True)) if group_by else {},
                config=config,
                distinct=distinct,
                runs=members,
            )
        )
    if len({a.name for a in arms}) < len(arms):  # a shortened name is not unique: spell out
        for arm in arms:
            arm.name = arm_name(label, arm.distinct, limit=len(keys))
    arms.sort(key=lambda a: [natural_key(v) for v in a.distinct.values()])
    return arms, split_note(label, arms, keys) if len(arms) > 1 else None


def build_arms(
    runs: Sequence, group_by: Sequence[str] = (), algos: Sequence[str] = ()
) -> tuple[list[Arm], list[str], list[str]]:
    """Split ``runs`` into arms of one configuration each; returns ``(arms, left_out, splits)``,
    notes on the runs left out and on every group split into several arms.

    Without ``group_by`` a group is an algorithm, in the order of ``algos`` (else by name).
    With it a group is one combination of the keys' values, in natural order (:func:`natural_key`),
    its arms in the order of ``algos``; runs without every ``group_by`` key are left out.
    A group of several configurations becomes several arms, and a note lists them.
    """
    left_out, splits = [], []
    if group_by:
        lacking = {r.info.run_id for r in runs if any(k not in run_params(r) for k in group_by)}
        if lacking:
            left_out.append(
                f"{formatting.runs(len(lacking))} without {' or '.join(group_by)} in their config "
                f"(run ids {', '.join(sorted(lacking))})"
            )
        runs = [r for r in runs if r.info.run_id not in lacking]
    groups: dict[tuple[str, ...], list] = {}
    for run in runs:
        groups.setdefault(_group_of(run, group_by), []).append(run)
    rank = {a: i for i, a in enumerate(algos)}
    if group_by:
        order = sorted(groups, key=lambda g: [natural_key(v) for v in g])
    else:
        order = sorted(groups, key=lambda g: (rank.get(g[0], len(rank)), g[0]))
    arms = []
    for group in order:
        group_arms, note = _arms_of_group(group, groups[group], group_by)
        group_arms.sort(key=lambda a: rank.get(a.algo, len(rank)))  # stable: keeps natural order
        arms += group_arms
        if note:
            splits.append(note)
    for arm in arms:
        left_out += _one_run_per_seed(arm)
    return arms, left_out, splits


def _one_run_per_seed(arm: Arm) -> list[str]:
    """Keep the latest run of each seed in ``arm``; notes on the others. Seeds are the arm's
    independent samples: the same seed trained again (a command run twice without a job key)
    is not another sample, and counting it would narrow every interval."""
    by_seed: dict[str, list] = {}
    for run in arm.runs:
        by_seed.setdefault(run.data.tags.get("seed", run.info.run_id), []).append(run)
    notes, kept = [], []
    for seed, runs in by_seed.items():
        runs.sort(key=lambda r: r.info.start_time or 0)
        kept.append(runs[-1])
        if len(runs) > 1:
            notes.append(
                f"{arm.name}: seed {seed} has {len(runs)} finished runs; the latest, "
                f"{runs[-1].info.run_id}, counts (one sample per seed), not "
                f"{', '.join(r.info.run_id for r in runs[:-1])}"
            )
    kept_ids = {r.info.run_id for r in kept}
    arm.runs = [r for r in arm.runs if r.info.run_id in kept_ids]
    return notes


def same_series_pairs(arms: Sequence[Arm]) -> list[tuple[str, str]]:
    """The pairs of arms that differ only in the ``group_by`` keys (the same configuration
    otherwise): what a study of those keys compares. With ``group_by=impl`` over several
    algorithms, each algorithm's walkers arm against its SB3 twin, never TD3 against SAC."""
    return [
        (a.name, b.name)
        for i, a in enumerate(arms)
        for b in arms[i + 1 :]
        if a.config == b.config and a.group_values != b.group_values
    ]


def series(arms: Sequence[Arm]) -> dict[str, str]:
    """For a score-vs-key plot: each arm's series (its configuration apart from the group_by
    keys), labelled by what differs between the series; "" when there is one series."""
    keys = differing_keys([a.config for a in arms])
    return {a.name: describe({k: a.config.get(k, ABSENT) for k in keys}, len(keys)) for a in arms}
