"""A study's reference arms: seeds a results bundle already holds, standing in for training.

A study file may declare an arm as ``{reference: <bundle folder>, arm: <its arm there>}``: only
the other arms train. Before anything runs, the bundle's runs of that arm are held to the study's
shared settings on each env (env, evaluation protocol, budget: the study's command line without
any arm's overrides) and to today's code (the update's fingerprint), as
:mod:`walkers.analysis.references` checks a report's references, and the bundle must hold every
seed the design may ask for (``0 .. seeds.max - 1``), so that the sequential rule reads the same
seeds it would have trained. Their scores then count as finished seeds of the arm.
"""

from __future__ import annotations

from collections.abc import Mapping

from walkers.ab.spec import Scores, StudySpec
from walkers.analysis.references import REFERENCE_KEY, check_like_for_like
from walkers.errors import ConfigError
from walkers.tracking.bundles import BundleRuns


def reference_scores(spec: StudySpec, shared: Mapping[str, dict]) -> Scores:
    """The scores of every reference arm on every env, checked; ``shared``: env -> the params
    the study's jobs share there (its command line and the env, no arm's overrides)."""
    scores: dict[tuple[str, str], dict[int, float]] = {}
    for arm in spec.arms:
        if arm.reference is None:
            continue
        try:
            bundle = BundleRuns(arm.reference, label_key=REFERENCE_KEY, arm=arm.of)
        except ConfigError as e:
            raise ConfigError(f"arm {arm.name!r}: {e}") from None
        for env in spec.envs:
            params = shared[env]
            budget = int(params["total_steps"])
            checked = check_like_for_like(bundle, params["env.id"], spec.score, params, budget)
            holder = f"arm {arm.name!r}: reference {arm.reference} holds"
            by_seed = _scores_by_seed(checked, spec.score, holder)
            lacking = [s for s in range(spec.seeds_max) if s not in by_seed]
            if lacking:
                raise ConfigError(
                    f"arm {arm.name!r}: reference {arm.reference} holds no seed {lacking[0]} "
                    f"of {env} (it has {sorted(by_seed) or 'none'}); the design may ask for seeds "
                    f"0-{spec.seeds_max - 1}: lower hydra.sweeper.seeds.max or export more seeds"
                )
            scores[(arm.name, env)] = {s: by_seed[s] for s in range(spec.seeds_max)}
    return scores


def _scores_by_seed(runs: list, score: str, holder: str) -> dict[int, float]:
    """Each seed's score; a seed held twice (two studies' arms of one name in one bundle) is
    refused, as its two runs are not two samples and either could be the arm's."""
    by_seed: dict[int, object] = {}
    for run in runs:
        seed = int(run.data.tags["seed"])
        if seed in by_seed:
            raise ConfigError(
                f"{holder} seed {seed} twice (runs {by_seed[seed].info.run_id} and "
                f"{run.info.run_id}): export one study's arm into the bundle it names"
            )
        by_seed[seed] = run
    return {seed: run.data.metrics[score] for seed, run in by_seed.items()}
