"""Finished runs in MLflow -> a comparison of arms (``python -m walkers.compare``).

An arm is one configuration, one seed per run (:mod:`walkers.analysis.arms`): runs are grouped
by their ``algo`` tag, or with ``group_by=<key>[,<key>]`` by the values of those config keys,
and a group whose runs differ in anything but the seed and keys that cannot change results is
split into arms named by what differs (``td3 (algo.hidden_sizes=[64, 64])``), never pooled; the
report lists every split. ``algos=[...]`` filters by algorithm and orders the arms. Only
comparable runs enter: the chosen env, one budget (``total_steps``), status FINISHED; everything
else is left out with a note in the report. Offline runs (``algo=dt``) count gradient steps, not
env steps: they get their own budget and their own learning-curve panel, they are compared with
the online runs on final return but not on AUC (a rate over different x-axes), and come from
one dataset, named in the report. Every per-run number comes from the run's logged eval curve
through the same :func:`walkers.analysis.stats.run_summary` the trainer uses; across seeds the
statistics are those of Agarwal et al. 2021 (:mod:`walkers.analysis.stats`), computed per arm
and pair by :func:`walkers.analysis.pairwise.compare_groups`; this module is the command:
which runs, their arms, the report and its MLflow run. Published
reference figures for the env (``published:`` in ``conf/env/<env>.yaml``) stand beside the
measured ones, marked as such, for the algorithms in the report.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from walkers.analysis.arms import (
    Arm,
    build_arms,
    parse_group_by,
    run_params,
    same_series_pairs,
    unknown_key_hint,
)
from walkers.analysis.comparison_data import (
    Comparison,
)
from walkers.analysis.pairwise import compare_groups
from walkers.analysis.references import (
    check_like_for_like,
    load_references,
    provenance,
    store_settings,
)
from walkers.analysis.report import verdict, write_report
from walkers.analysis.selection import (
    CURVE_METRIC,
    comparable_runs,
    load_seed_runs,
    published_figures,
)
from walkers.errors import ConfigError
from walkers.secrets import redacted_uri
from walkers.tracking import bundles
from walkers.tracking.client import connect, search_runs, side_run
from walkers.tracking.names import KIND_TAG

log = logging.getLogger("walkers")

SCORES = ("final/return_mean", "final/return_last10", "final/auc")


def _check(cfg: DictConfig) -> None:
    if cfg.score not in SCORES:
        raise ConfigError(f"score={cfg.score!r} is not allowed: must be one of {', '.join(SCORES)}")
    if not 0 < cfg.confidence < 1:
        raise ConfigError(f"confidence={cfg.confidence!r} is not allowed: must be in (0, 1)")
    if not (isinstance(cfg.n_resamples, int) and cfg.n_resamples >= 100):
        raise ConfigError(f"n_resamples={cfg.n_resamples!r} is not allowed: must be >= 100")
    for key in ("total_steps", "gradient_steps"):
        value = cfg[key]
        each = value.values() if key == "gradient_steps" and OmegaConf.is_dict(value) else [value]
        if not all(v is None or (isinstance(v, int) and v > 0) for v in each):
            shown = OmegaConf.to_container(value) if OmegaConf.is_config(value) else value
            per_algo = " or {algo: steps, ...}" if key == "gradient_steps" else ""
            raise ConfigError(
                f"{key}={shown!r} is not allowed: must be null, a positive integer{per_algo}"
            )


def _check_group_by(group_by: list[str], runs: list, where: str) -> None:
    """Every ``group_by`` key must be a config key of some training run of the experiment."""
    params = [run_params(r) for r in runs if r.data.tags.get(KIND_TAG, "train") == "train"]
    for key in group_by:
        if not any(key in p for p in params):
            raise ConfigError(
                f"group_by={key!r} is not a config key of any run in {where}: "
                + unknown_key_hint(key, params)
            )


def compare(cfg: DictConfig, beside: dict | None = None) -> tuple[Comparison, Path, str | None]:
    """Build the comparison ``cfg`` asks for, write the report; returns it, its dir, a UI link.
    ``beside``: env id -> the settings references are held to (see :func:`build_comparison`)."""
    comparison, client = build_comparison(cfg, beside)
    out = Path(cfg.out)
    return comparison, out, publish(comparison, client, cfg, out)


def publish(comparison: Comparison, client, cfg: DictConfig, out: Path) -> str | None:
    """Write ``comparison``'s report to ``out`` and, with ``log_report``, log it as an MLflow
    run; returns its UI link."""
    files = write_report(comparison, out, source=source_name(cfg))
    if not cfg.log_report:
        return None
    return _log_report(client or connect(cfg.tracking.uri), cfg, comparison, files)


def build_comparison(cfg: DictConfig, beside: dict | None = None):
    """The comparison ``cfg`` asks for (arms as the report forms them), and the store's client.

    ``beside``: env id -> the params reference arms are held to there (a study's shared
    settings); by default the settings every store run on the env shares."""
    _check(cfg)
    client, histories, runs = open_runs(cfg)
    algos = list(cfg.algos)
    group_by = parse_group_by(cfg.group_by)
    references = load_references(cfg.get("reference") or [])
    mine, budget = store_settings(runs, cfg.env.id, cfg.total_steps)
    if beside and cfg.env.id in beside:
        mine = beside[cfg.env.id]
    if mine is None and references:  # nothing of the store's on the env: held to each other
        mine, budget = store_settings(references[0].runs, cfg.env.id, budget)
    for reference in references:
        check_like_for_like(reference, cfg.env.id, cfg.score, mine, budget)
    source_of = {r.info.run_id: histories for r in runs}
    for reference in references:
        source_of |= {r.info.run_id: reference for r in reference.runs}
        runs = runs + reference.runs
    _check_group_by(group_by, runs, runs_place(cfg))
    chosen, budgets, notes = comparable_runs(
        runs, cfg.env.id, algos, cfg.total_steps, cfg.gradient_steps, cfg.dataset
    )
    loaded = {}
    for source in {id(s): s for s in source_of.values()}.values():
        mine = [r for r in chosen if source_of[r.info.run_id] is source]
        loaded |= load_seed_runs(source, mine, cfg.env.threshold)
    notes += [
        f"run {r.info.run_id} ({r.data.tags.get('algo')}, seed {r.data.tags.get('seed')}) "
        f"logged no {CURVE_METRIC}"
        for r in chosen
        if r.info.run_id not in loaded
    ]
    arms, lacking, splits = build_arms(
        [r for r in chosen if r.info.run_id in loaded], group_by, algos
    )
    notes += lacking
    found_algos = {a.algo for a in arms}
    missing = [a for a in algos if a not in found_algos]
    if missing or not arms:
        found = sorted({r.data.tags.get("algo") for r in runs if r.data.tags.get("algo")})
        raise ConfigError(
            f"algos={algos or sorted(found_algos)} has no finished {cfg.env.id} runs for "
            f"{', '.join(missing) or 'any'} in {runs_place(cfg)} "
            f"(algorithms with runs there: {', '.join(found) or 'none'})"
            + (f"; left out: {'; '.join(notes)}" if notes else "")
        )
    comparison = compare_groups(
        {arm.name: [loaded[r.info.run_id] for r in arm.runs] for arm in arms},
        [arm.name for arm in arms],
        env_id=cfg.env.id,
        threshold=cfg.env.threshold,
        budgets=budgets,
        score=cfg.score,
        confidence=cfg.confidence,
        n_resamples=cfg.n_resamples,
        seed=cfg.seed,
        arms={arm.name: arm for arm in arms},
        smallest_effect=cfg.smallest_effect,
        smallest_effect_abs=cfg.smallest_effect_abs,
        # a study of group_by keys compares arms that differ only in them, where there are such
        pairs=(same_series_pairs(arms) or None) if group_by else None,
    )
    comparison.left_out = notes
    comparison.group_by = group_by
    comparison.splits = splits
    comparison.published = published_figures(cfg.env, list(dict.fromkeys(a.algo for a in arms)))
    comparison.references = [
        provenance(ref, arms_of) for ref in references if (arms_of := _arms_from(ref, arms))
    ]
    return comparison, client


def open_runs(cfg: DictConfig) -> tuple:
    """Where the compared runs are: ``(client, histories, runs)``. The store's experiment
    (its client reads their histories), or with ``bundle=PATH`` a bundle read where it lies,
    without a store (client None: a report is logged to ``tracking.uri`` only if asked)."""
    if cfg.get("bundle"):
        bundle = bundles.BundleRuns(Path(str(cfg.bundle)))
        return None, bundle, bundle.runs
    client = connect(cfg.tracking.uri)
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    if experiment is None:
        names = [e.name for e in client.search_experiments()]
        raise ConfigError(
            f"tracking.experiment={cfg.tracking.experiment!r} is not in {cfg.tracking.uri}; "
            f"experiments there: {', '.join(names) or 'none'}"
        )
    return client, client, search_runs(client, experiment.experiment_id)


def runs_place(cfg: DictConfig) -> str:
    """Where the compared runs are, as an error message names it."""
    if cfg.get("bundle"):
        return f"bundle {str(cfg.bundle)!r}"
    return f"experiment {cfg.tracking.experiment!r}"


def source_name(cfg: DictConfig) -> str:
    """How a report names where its runs came from (``source=`` overrides it)."""
    if cfg.get("source"):
        return str(cfg.source)
    if cfg.get("bundle"):
        return f"bundle {cfg.bundle}"
    return f"{redacted_uri(cfg.tracking.uri)}, {runs_place(cfg)}"


def _arms_from(reference, arms: list[Arm]) -> dict[str, list[str]]:
    """The arms whose runs came from ``reference``: arm name -> its run ids."""
    ids = {r.info.run_id for r in reference.runs}
    return {
        arm.name: [r.info.run_id for r in arm.runs]
        for arm in arms
        if any(r.info.run_id in ids for r in arm.runs)
    }


#: MLflow's limits on a run name and a tag value.
MAX_NAME, MAX_TAG = 250, 8000


def budget_params(budgets: dict) -> dict[str, int]:
    """``budget.<axis>``, or ``budget.<axis>.<algo>`` where offline algorithms differ."""
    params = {}
    for axis, budget in budgets.items():
        if isinstance(budget, dict):
            params |= {f"budget.{axis}.{mlflow_key(algo)}": b for algo, b in budget.items()}
        else:
            params[f"budget.{axis}"] = budget
    return params


def mlflow_key(name: str) -> str:
    """An arm's name as part of an MLflow param/metric key (letters, digits, ``_-. :`` only):
    ``td3 (algo.hidden_sizes=[64, 64])`` -> ``td3 algo.hidden_sizes:64 64``."""
    key = re.sub(r"[^\w.\- :]", "", name.replace("=", ":").replace(",", " "))
    return re.sub(" +", " ", key).strip()[:200]


def _log_report(client, cfg: DictConfig, comparison: Comparison, files: list[Path]) -> str:
    """The report as an MLflow run of its own, beside the runs it compares."""
    names = [r.algo for r in comparison.algos]
    algorithms = list(dict.fromkeys(r.algorithm for r in comparison.algos))
    study = f"-by-{'+'.join(comparison.group_by)}" if comparison.group_by else ""
    with side_run(
        client,
        cfg.tracking.experiment,
        run_name=f"report-{'-vs-'.join(algorithms)}{study}-{comparison.env_id}"[:MAX_NAME],
        tags={
            KIND_TAG: "report",
            "env": comparison.env_id,
            "algos": ",".join(algorithms),
            "arms": "; ".join(names)[:MAX_TAG],
            "mlflow.note.content": verdict(comparison)[:MAX_TAG],
        },
        spool_dir=Path(cfg.work_dir) / "spool",
    ) as tracker:
        tracker.log_params(
            {
                "score": comparison.score,
                **budget_params(comparison.budgets),
                "confidence": comparison.confidence,
                "n_resamples": cfg.n_resamples,
                **{f"runs.{mlflow_key(r.algo)}": len(r.runs) for r in comparison.algos},
            }
        )
        tracker.log_metrics(
            {
                f"{mlflow_key(r.algo)}/{key}": value
                for r in comparison.algos
                for key, value in r.as_dict().items()
                if isinstance(value, float | int) and math.isfinite(value)
            },
            step=0,
        )
        for path in files:
            tracker.log_artifact(path)
    return tracker.url
