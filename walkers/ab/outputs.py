"""What a study leaves when it ends: its report and its bundle, written by the study itself.

At its verdict (or its maximum seeds) a study writes the report ``walkers.compare`` would (each
env's, then the suite's over several envs: aggregates, performance profile, sample-efficiency
curves) under ``reports/<experiment>/``, and the bundle of its runs
(:mod:`walkers.tracking.bundles`) in ``reports/<experiment>/bundle``, replaced when the same
command ends it again. Neither can fail the study (a failure is one warning line): its answers
are already on its MLflow run.
"""

from __future__ import annotations

import logging
from pathlib import Path

from hydra.types import RunMode
from omegaconf import DictConfig, open_dict

from walkers.ab.spec import StudySpec
from walkers.analysis.comparison import compare
from walkers.analysis.references import recorded_fingerprint
from walkers.analysis.suite_report import compare_suite
from walkers.tracking import bundles
from walkers.tracking.names import FINISHED

log = logging.getLogger("walkers")


def report_config(config_loader, config: DictConfig, spec: StudySpec) -> DictConfig:
    """``walkers.compare``'s config for the study: its store, experiment, envs and score."""
    overrides = [f"env={spec.envs[0]}", f"score={spec.score}"]
    if spec.suite:
        overrides.append(f"envs=[{','.join(spec.envs)}]")
    cfg = config_loader.load_configuration("compare", overrides, RunMode.RUN)
    with open_dict(cfg):
        del cfg["hydra"]
        cfg.reference = [
            arm.reference + (f"#{arm.of}" if arm.of else "") for arm in spec.arms if arm.reference
        ]
        cfg.tracking = config.tracking  # by reference: a store's URI is never an override
        cfg.work_dir = config.work_dir
    return cfg


def write_results(
    config_loader, config: DictConfig, spec: StudySpec, client, shared: dict[str, dict]
) -> list[str]:
    """Write the study's report and bundle; returns what to print (where they are).
    ``shared``: env -> the params the study's jobs share there (what its references match)."""
    experiment = config.tracking.experiment
    lines = []
    try:
        cfg = report_config(config_loader, config, spec)
        beside = {params["env.id"]: params for params in shared.values()}
        if spec.suite:
            _, out = compare_suite(cfg, beside)
        else:
            _, out, _ = compare(cfg, beside)
        lines.append(f"report: {out / 'report.md'}")
    except Exception as e:  # e.g. runs without evaluations: say so, keep the answers
        log.warning("study %r: no report: %s", spec.name, e)
    try:
        experiment_id = client.get_experiment_by_name(experiment).experiment_id
        runs = bundles.runs_to_export(client, experiment_id, spec.name, {}, [FINISHED])
        done = bundles.export_runs(
            client,
            experiment,
            runs,
            Path("reports") / experiment / "bundle",
            f"study={spec.name}; statuses FINISHED",
            replace=True,
            fingerprint=recorded_fingerprint,
        )
    except Exception as e:  # a store gone away at the end: the answers are on the study's run
        log.warning("study %r: no bundle: %s (python -m walkers.export writes it)", spec.name, e)
        return lines
    lines.append(
        f"bundle: {done.path} ({done.runs} runs, {done.bytes / 1024:.1f} KiB; "
        f"`python -m walkers.ingest bundle={done.path}` puts them into another store)"
    )
    return lines
