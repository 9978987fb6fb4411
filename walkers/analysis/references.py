"""Reference arms: seeds from a results bundle, compared without being rerun.

``walkers.compare ... reference=[results/original]`` puts a bundle's runs beside the store's. A
reference's runs are used only when the comparison is like for like, checked run by run before
anything is computed, and refused in one line naming the first difference:

- the same env id (its version included) and the same env settings;
- the same evaluation protocol (``eval_every``, ``eval_episodes``) and the score's metric;
- the same budget (``total_steps``);
- the same algorithm code: the run's update fingerprint, kept in the bundle, equals the one
  today's code gives for the run's config (:mod:`walkers.analysis.fingerprint`).

Their runs carry the param ``reference=<bundle name>``: they never pool with the store's runs of
the same configuration (an arm is split where they meet), and the report lists the arms that came
from references with their provenance.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

import yaml

from walkers.analysis.arms import is_not_the_experiment, run_params
from walkers.errors import ConfigError
from walkers.tracking.bundles import FINGERPRINT_TAG, BundleRuns
from walkers.tracking.names import FINISHED, KIND_TAG, total_steps_of
from walkers.training.provenance import code_digests

#: The param a reference's runs carry: the bundle's name.
REFERENCE_KEY = "reference"
#: What makes two runs' evaluations the same measurement, beside the env's settings.
PROTOCOL = ("eval_every", "eval_episodes")


def load_references(paths) -> list[BundleRuns]:
    """``PATH`` (every run of a bundle) or ``PATH#ARM`` (one arm of the study that made it)."""
    references = []
    for given in map(str, paths):
        path, _, arm = given.partition("#")
        references.append(BundleRuns(Path(path), label_key=REFERENCE_KEY, arm=arm or None))
    names = [ref.name for ref in references]
    if len(set(names)) < len(names):
        raise ConfigError(f"reference={list(map(str, paths))} names one bundle twice: {names}")
    return references


def _training(runs) -> list:
    return [
        r
        for r in runs
        if r.info.status == FINISHED and r.data.tags.get(KIND_TAG, "train") == "train"
    ]


def store_settings(store_runs: list, env_id: str, budget: int | None):
    """What a reference is held to in a store: the params every finished training run on
    ``env_id`` shares (None if it has none; a key its arms set differently is not held), and
    the budget (given, else the most common)."""
    ours = [r for r in _training(store_runs) if r.data.tags.get("env") == env_id]
    if not ours:
        return None, budget
    if budget is None:
        budget = int(Counter(map(total_steps_of, ours)).most_common(1)[0][0])
    every = [run_params(r) for r in ours]
    shared = {k: v for k, v in every[0].items() if all(p.get(k) == v for p in every[1:])}
    return shared, budget


def check_like_for_like(
    reference: BundleRuns,
    env_id: str,
    score: str,
    mine: dict | None,
    budget: int | None,
) -> list:
    """Refuse, in one line, a reference whose runs are not like for like with ``mine`` (the
    params of the runs it stands beside) on ``env_id``, or with today's code; see the module's
    list. Returns its finished training runs on ``env_id``."""
    name = reference.name
    own = _training(reference.runs)
    on_env = [r for r in own if r.data.tags.get("env") == env_id]
    if not on_env:
        envs = sorted({r.data.tags.get("env", "?") for r in own}) or ["none"]
        raise ConfigError(
            f"reference {name!r} is not like for like: its runs are of {', '.join(envs)}, "
            f"not {env_id}"
        )
    for run in on_env:
        params = run_params(run)
        where = f"reference {name!r} is not like for like: run {run.info.run_id}"
        if budget is not None and params.get("total_steps") != str(budget):
            raise ConfigError(
                f"{where} has total_steps={params.get('total_steps')}, this comparison {budget}"
            )
        if mine is not None:
            keys = [*PROTOCOL, *sorted(k for k in mine if _env_key(k))]
            for key in keys:
                if params.get(key) != mine.get(key):
                    raise ConfigError(
                        f"{where} has {key}={params.get(key, '<unset>')}, the runs it stands "
                        f"beside {mine.get(key, '<unset>')}"
                    )
        if score not in run.data.metrics:
            raise ConfigError(f"{where} has no {score}")
        _check_code(reference, run, where)
    return on_env


def _env_key(key: str) -> bool:
    return key.startswith("env.") and not is_not_the_experiment(key)


def recorded_fingerprint(tags: Mapping[str, str], config: str | None) -> list[float] | None:
    """The update fingerprint an export records for a run: the one it carries (an imported
    run's, recorded by the code that trained it), else today's code's where today's code trained
    it; none for a run trained by more than one code (resumed under another: no single update
    made it, whatever it carries)."""
    from walkers.analysis.fingerprint import of_run  # torch: see _check_code

    if len(code_digests(tags)) > 1:
        return None
    known = tags.get(FINGERPRINT_TAG)
    return json.loads(known) if known else of_run(tags, config)


def _check_code(reference: BundleRuns, run, where: str) -> None:
    record = reference.records[run.info.run_id]
    recorded = record.get("fingerprint")
    digests = code_digests(run.data.tags)
    if len(digests) > 1:  # a bundle written before exports knew: its fingerprint is one code's
        raise ConfigError(
            f"{where} was trained by {len(digests)} codes in turn (resumed under another: "
            f"code digests {' then '.join(digests)}): no one update made it; rerun the arm"
        )
    if not recorded:
        raise ConfigError(
            f"{where} carries no update fingerprint (exported by other code than trained it, "
            "a twin or an offline run): its code cannot be checked; export it from the commit "
            f"that trained it ({run.data.tags.get('git_commit', 'unknown')})"
        )
    # here, not at the top: a fingerprint is computed by today's torch code, and a report
    # without references (most of them) is made without importing torch
    from walkers.analysis.fingerprint import differs, update_fingerprint

    algo = (yaml.safe_load(record.get("config") or "") or {}).get("algo") or {}
    difference = differs(recorded, update_fingerprint(algo))
    if difference:
        raise ConfigError(
            f"{where} was trained by another update than today's {run.data.tags.get('algo')} "
            f"({difference}): rerun the arm, or compare with the commit that trained it "
            f"({run.data.tags.get('git_commit', 'unknown')})"
        )


def provenance(reference: BundleRuns, arm_runs: dict[str, list[str]]) -> dict:
    """What the report says of a reference: where it came from, what made it, which arms."""
    runs = [r for r in reference.runs if any(r.info.run_id in ids for ids in arm_runs.values())]
    source = reference.document["source"]
    hours = [r.data.metrics.get("final/cpu_hours") for r in runs]
    return {
        "name": reference.name,
        "path": str(reference.path),
        "arms": sorted(arm_runs),
        "runs": len(runs),
        "experiment": source.get("experiment"),
        "selection": source.get("selection"),
        "commits": sorted({r.data.tags.get("git_commit", "unknown") for r in runs}),
        "packages": sorted({r.data.tags.get("walkers.packages", "unknown") for r in runs}),
        "devices": sorted({r.data.params.get("device", "unknown") for r in runs}),
        "cpu_hours": math.fsum(h for h in hours if h is not None) if any(hours) else None,
    }
