"""A study's MLflow run and what its jobs left in MLflow.

The study's run (tag ``walkers.kind=ab``, ``walkers.ab=<name>``) is created by the first command
and reopened by every rerun; its params are the design (refused if a rerun's differs), its jobs'
runs nest under it, and each round logs the interim answers: metrics ``ab/questions_open`` and
``ab/seeds_run`` per look, tags ``answer.<question>``, the artifact ``rounds/look_<k>.md``.
A job's run is found by its job key (``ab/<study>/<arm>/<env>/<seed>``); only FINISHED runs
count, one per key.
"""

from __future__ import annotations

import logging
import math
import tempfile
from collections.abc import Mapping
from pathlib import Path

from walkers import PROJECT_ROOT
from walkers.ab.rounds import Standing
from walkers.ab.spec import Scores, StudySpec
from walkers.analysis import formatting
from walkers.analysis.arms import arm_config, run_params
from walkers.analysis.sequential import Design
from walkers.errors import ConfigError
from walkers.tracking.bundle_format import BundleRuns
from walkers.tracking.client import (
    Tracker,
    get_or_create_experiment,
    quoted,
    search_runs,
    tags_equal,
)
from walkers.tracking.names import (
    FAILED,
    FINISHED,
    JOB_KEY_TAG,
    KIND_TAG,
    LOGGED_THROUGH_TAG,
    STUDY_KIND,
    STUDY_TAG,
    differing_keys,
    status_after,
    total_steps_of,
)
from walkers.training.provenance import DIVERGED_TAG

log = logging.getLogger("walkers")


def open_study_run(client, experiment: str, spec: StudySpec, spool_dir) -> Tracker:
    """The study's run, reopened (its design checked) or started."""
    experiment_id = get_or_create_experiment(client, experiment)
    query = tags_equal({KIND_TAG: STUDY_KIND, STUDY_TAG: spec.name})
    earlier = search_runs(client, experiment_id, query)
    design = spec.design_params()
    if earlier:
        stored = earlier[0].data.params
        for key, value in design.items():
            if key in stored and stored[key] != value:
                raise ConfigError(
                    f"study {spec.name!r} in experiment {experiment!r} was started with "
                    f"{key}={stored[key]!r}, not {value!r}: a study's test is fixed when it "
                    "starts; restore the study file or give the new design a new name"
                )
        tracker = Tracker.reopen(client, earlier[0].info.run_id, spool_dir)
        log.info("study %r: continuing its MLflow run %s", spec.name, tracker.run_id)
        return tracker
    tags = {KIND_TAG: STUDY_KIND, STUDY_TAG: spec.name}
    tracker = Tracker.start(client, experiment, f"ab-{spec.name}", tags, spool_dir)
    try:
        tracker.log_params(design)
    except BaseException as e:
        tracker.end(status_after(e))
        raise
    return tracker


def log_deciding_looks(tracker: Tracker, design: Design) -> None:
    """Tags ``ab.deciding_looks`` and ``ab.equal_looks``: the seeds per arm of the looks that
    can answer "better" (and "equal") at all; the others can only say "continue"."""
    tracker.set_tags(
        {
            "ab.deciding_looks": ",".join(str(design.looks[k]) for k in design.deciding_looks()),
            "ab.equal_looks": ",".join(str(design.looks[k]) for k in design.equal_looks()),
        }
    )


def job_runs(client, experiment: str, spec: StudySpec) -> list:
    """Every run of the study's jobs (any status)."""
    experiment_obj = client.get_experiment_by_name(experiment)
    if experiment_obj is None:
        return []
    key = quoted(f"{spec.job_key_prefix}%")
    query = f"tags.`{JOB_KEY_TAG}` LIKE {key}"
    return search_runs(client, experiment_obj.experiment_id, query)


def finished_scores(runs: list, spec: StudySpec) -> Scores:
    """(arm, env) -> {seed: score} of the FINISHED runs (one per job key: never a seed twice)."""
    scores: dict[tuple[str, str], dict[int, float]] = {}
    for run in runs:
        place = spec.parse_job_key(run.data.tags.get(JOB_KEY_TAG, ""))
        if place is None or run.info.status != FINISHED:
            continue
        arm, env, seed = place
        if spec.score not in run.data.metrics:
            continue
        by_seed = scores.setdefault((arm, env), {})
        if seed in by_seed:
            log.warning("job %s has two FINISHED runs: counting one", run.data.tags[JOB_KEY_TAG])
            continue
        by_seed[seed] = run.data.metrics[spec.score]
    return scores


def diverged(runs: list, keys: set[str]) -> list:
    """The runs of the jobs ``keys`` that ended FAILED because their updates diverged."""
    return [
        run
        for run in runs
        if run.info.status == FAILED
        and DIVERGED_TAG in run.data.tags
        and run.data.tags.get(JOB_KEY_TAG) in keys
    ]


def steps_logged(runs: list) -> dict[str, int]:
    """job key -> the most steps an unfinished run of the job logged (what its resume goes on
    from, about); jobs that never logged are absent."""
    logged: dict[str, int] = {}
    for run in runs:
        key, mark = (
            run.data.tags.get(JOB_KEY_TAG),
            run.data.tags.get(LOGGED_THROUGH_TAG),
        )
        if key and mark is not None and run.info.status != FINISHED:
            logged[key] = max(logged.get(key, 0), int(mark))
    return logged


def cpu_hours_by_arm(runs: list, spec: StudySpec) -> dict[str, tuple[float, int, int]]:
    """arm -> (the CPU-hours of its FINISHED runs that counted them, how many did, how many
    FINISHED): what the study cost so far, over every env and seed."""
    hours: dict[str, tuple[float, int, int]] = {}
    for run in runs:
        place = spec.parse_job_key(run.data.tags.get(JOB_KEY_TAG, ""))
        if place is None or run.info.status != FINISHED:
            continue
        total, counted, finished = hours.get(place[0], (0.0, 0, 0))
        spent = run.data.metrics.get("final/cpu_hours", math.nan)  # nan: not counted throughout
        if math.isfinite(spent):
            total, counted = total + spent, counted + 1
        hours[place[0]] = (total, counted, finished + 1)
    return hours


def cpu_hours_line(hours: dict[str, tuple[float, int, int]]) -> str:
    """``CPU-hours of the finished runs: td3 12.31, reinforce 1.20 (4 of 5 runs counted)``."""
    parts = [f"{arm} {formatting.cpu_hours(*counts)}" for arm, counts in hours.items()]
    return "CPU-hours of the finished runs: " + (", ".join(parts) if parts else "none yet")


def hours_per_step(runs: list, spec: StudySpec) -> dict[tuple[str, str], float]:
    """(arm, env) -> CPU-hours an env step of its jobs costs, as its runs measured it: the mean
    over its FINISHED runs that counted CPU time, else its unfinished run furthest along (past
    a warm-up, whose random actions cost less than learning). Absent: nothing measured yet."""
    finished: dict[tuple[str, str], list[float]] = {}
    furthest: dict[tuple[str, str], tuple[int, float]] = {}
    for run in runs:
        place = spec.parse_job_key(run.data.tags.get(JOB_KEY_TAG, ""))
        if place is None:
            continue
        arm_env = place[:2]
        if run.info.status == FINISHED:
            hours = run.data.metrics.get("final/cpu_hours", math.nan)
            steps = float(total_steps_of(run) or "nan")
            if math.isfinite(hours) and steps > 0:
                finished.setdefault(arm_env, []).append(hours / steps)
            continue
        hours = run.data.metrics.get("perf/cpu_hours", math.nan)
        steps = int(run.data.tags.get(LOGGED_THROUGH_TAG, 0))
        if math.isfinite(hours) and steps > furthest.get(arm_env, (0, 0.0))[0]:
            furthest[arm_env] = (steps, hours / steps)
    rates = {key: rate for key, (_, rate) in furthest.items()}
    return rates | {key: math.fsum(r) / len(r) for key, r in finished.items()}


def hours_per_step_in_results(algo: str, env_id: str) -> float | None:
    """CPU-hours an env step of ``algo`` on ``env_id`` cost in the committed results bundles
    (``results/*/bundle``: their FINISHED runs that counted CPU time), for a study whose arm
    has no run of its own yet; None where none has one."""
    rates = []
    for path in sorted((PROJECT_ROOT / "results").glob("*/bundle")):
        for run in BundleRuns(path).runs:
            hours = run.data.metrics.get("final/cpu_hours", math.nan)
            steps = float(total_steps_of(run) or "nan")
            tags = run.data.tags
            if (
                (tags.get("algo"), tags.get("env")) == (algo, env_id)
                and run.info.status == FINISHED
                and math.isfinite(hours)
                and steps > 0
            ):
                rates.append(hours / steps)
    return math.fsum(rates) / len(rates) if rates else None


def expected_cost(
    launches: list[tuple[str, str, list[int]]],
    steps_left: list[int],
    rates: Mapping[tuple[str, str], float],
    parallel: int | None,
    from_results: set[tuple[str, str]] | frozenset = frozenset(),
) -> str:
    """What a round will cost, said before it starts: its CPU-hours at the rates its arms' runs
    measured (:func:`hours_per_step`; ``from_results``: arms with no run of their own, rated by
    :func:`hours_per_step_in_results`), and its wall time with ``parallel`` jobs at a time,
    the launches taken in order by whichever job slot frees first (one torch thread a job, so
    a job's wall time is about its CPU time on a machine it has to itself)."""
    unknown = sorted({f"{arm} on {env}" for arm, env, _ in launches if (arm, env) not in rates})
    if unknown:
        return (
            f"its CPU-hours are not known yet: no run of {', '.join(unknown)} has measured them "
            "(the next round says)"
        )
    hours = [
        rates[(arm, env)] * left for (arm, env, _), left in zip(launches, steps_left, strict=True)
    ]
    borrowed = sorted({f"{arm} on {env}" for arm, env, _ in launches if (arm, env) in from_results})
    said = f"about {math.fsum(hours):.3g} CPU-hours at the CPU time its arms' runs measured" + (
        f" ({', '.join(borrowed)}: the committed results' runs of its algorithm)"
        if borrowed
        else ""
    )
    if not parallel:
        return said
    slots = [0.0] * min(parallel, len(hours))
    for h in hours:  # each launch to the job slot that frees first
        slots[slots.index(min(slots))] += h
    at_once = f"{len(slots)} jobs at a time" if len(slots) > 1 else "one job at a time"
    return f"{said}; about {max(slots):.3g} h of wall time, {at_once}"


def check_arms_unchanged(runs: list, spec: StudySpec, configs: Mapping[tuple[str, str], dict]):
    """Refuse, in one line, an arm whose configuration is not that of its runs so far (the
    study file edited): a changed arm is a new arm, under a new name."""
    for run in runs:
        place = spec.parse_job_key(run.data.tags.get(JOB_KEY_TAG, ""))
        if place is None or (place[0], place[1]) not in configs:
            continue
        if not run.data.params:  # killed between its start and its config's logging: it
            continue  # never trained, and has no configuration to hold the arm to
        arm, env, _ = place
        then, now = arm_config(run_params(run)), arm_config(configs[(arm, env)])
        changed = differing_keys([then, now])
        if changed:
            key = changed[0]
            raise ConfigError(
                f"study {spec.name!r}: arm {arm!r} on {env} has changed since its runs started "
                f"({key}: {then.get(key, '<unset>')} -> {now.get(key, '<unset>')}"
                f"{f', and {len(changed) - 1} more' if len(changed) > 1 else ''}): an arm is one "
                f"configuration; restore it, or declare the new one as an arm of another name"
            )


def log_standing(
    tracker: Tracker,
    standing: Standing,
    seeds_run: int,
    hours: dict[str, tuple[float, int, int]],
) -> None:
    """One round's interim answers, and the CPU-hours spent per arm, on the study's run."""
    step = max(standing.look, 0)
    open_ = sum(not q.answer.settled for q in standing.questions)
    spent = {f"ab/cpu_hours.{arm}": total for arm, (total, _, _) in hours.items()}
    tracker.log_metrics({"ab/questions_open": open_, "ab/seeds_run": seeds_run} | spent, step=step)
    tracker.set_tags({f"answer.{_tag(q.name)}": q.answer.decision for q in standing.questions})
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"look_{step}.md"
        path.write_text(standing_table(standing))
        tracker.log_artifact(path, "rounds")
    tracker.flush()


def _tag(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "")


def standing_table(standing: Standing) -> str:
    """The answers as a markdown table."""
    rows = [
        "| question | answer | seeds per arm | mean difference (normalized) | p (superiority) "
        "| power for the smallest difference |",
        "|---|---|---|---|---|---|",
    ]
    for q in standing.questions:
        r = q.answer
        power = "" if r.power != r.power else f"{r.power:.2f}"
        rows.append(
            f"| {q.name} | {r.decision} | {r.seeds} | {r.difference:+.1f} | {r.p_value:.4f} "
            f"| {power} |"
        )
    return "\n".join(rows) + "\n"
