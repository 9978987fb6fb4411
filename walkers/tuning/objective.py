"""What a study optimizes and how a trial is scored: the direction (from
:data:`walkers.metrics.METRIC_DIRECTIONS`, a sweep's own setting checked against it), a resumed
study's objective, and a trial's outcome told to the study (pruned, diverged, failed, scored).
"""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Sequence
from typing import Any

import optuna
from hydra.core.utils import JobReturn
from hydra_plugins.hydra_optuna_sweeper.config import Direction
from optuna.study import StudyDirection
from optuna.trial import TrialState

from walkers.errors import ConfigError
from walkers.metrics import MAXIMIZE, MINIMIZE, metric_direction
from walkers.tuning.studies import counted_trials
from walkers.tuning.trial import PRUNED_AT

log = logging.getLogger("walkers")

DONE = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
#: Study user attribute: the metric its trials are scored by (a resumed study must keep it).
METRIC_ATTR = "walkers.optimized_metric"


# --- the direction --------------------------------------------------------------------------
def given_direction(direction: Any) -> str | None:
    """The direction a sweep file or the command line set, or None where it is left unset.

    Unset is ``null``, or hydra-optuna-sweeper's own default for a sweep that does not mention
    it: the enum ``Direction.minimize`` (what a yaml file or command line sets is a string).
    """
    if direction is None or isinstance(direction, Direction):
        return None
    if isinstance(direction, Sequence) and not isinstance(direction, str):
        if len(direction) != 1:
            raise ConfigError(
                f"hydra.sweeper.direction={list(direction)} is not allowed: a walkers sweep "
                "optimizes one metric (optimized_metric); leave direction null"
            )
        (direction,) = direction
    direction = direction.name if isinstance(direction, Direction) else str(direction)
    if direction not in (MAXIMIZE, MINIMIZE):
        raise ConfigError(
            f"hydra.sweeper.direction={direction!r} is not allowed: must be null "
            f"(it follows optimized_metric), {MAXIMIZE} or {MINIMIZE}"
        )
    return direction


def sweep_direction(metric: str, direction: Any) -> str:
    """The study's direction: ``metric``'s; a direction the sweep sets itself must agree."""
    wanted = metric_direction(metric)
    given = given_direction(direction)
    if given is not None and given != wanted:
        raise ConfigError(
            f"hydra.sweeper.direction={given} contradicts optimized_metric={metric}, which is "
            f"{wanted}d: leave direction null (it follows the metric)"
        )
    return wanted


def check_objective(study: optuna.Study, storage: str | None, metric: str) -> None:
    """A resumed study keeps its metric and direction: scores of another kind do not compare.

    A study from before the metric was stored is checked by its direction alone.
    """
    stored = study.user_attrs.get(METRIC_ATTR)
    stored_direction, direction = study.direction.name.lower(), metric_direction(metric)
    if stored_direction != direction or stored not in (None, metric):
        raise ConfigError(
            f"optimized_metric={metric} ({direction}d) cannot continue study "
            f"{study.study_name!r} in {storage}: it {stored_direction}s {stored or 'its metric'}; "
            "name a new study with hydra.sweeper.study_name=<name>"
        )
    if stored is None:
        study.set_user_attr(METRIC_ATTR, metric)


# --- scoring a trial ------------------------------------------------------------------------
def worst_finite(study: optuna.Study) -> float:
    """The worst score among completed trials (the floor of the range if there is none)."""
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    values = [t.value for t in complete if t.value is not None and math.isfinite(t.value)]
    maximize = study.direction == StudyDirection.MAXIMIZE
    if not values:
        return -sys.float_info.max if maximize else sys.float_info.max
    return min(values) if maximize else max(values)


def infinitely_bad(study: optuna.Study) -> float:
    """The infinity that ranks below every score: -inf when maximizing, inf when minimizing."""
    return -math.inf if study.direction == StudyDirection.MAXIMIZE else math.inf


def trial_value(results: Sequence[JobReturn]) -> float:
    """A trial's value: its job's, or the mean over its seeds' jobs (NaN if any diverged).
    Re-raises the first exception a job raised."""
    return float(sum(float(r.return_value) for r in results) / len(results))


def record_outcome(
    study: optuna.Study, trial: optuna.Trial, results: Sequence[JobReturn]
) -> Exception | None:
    """Tell the study how a trial's jobs (one per seed) ended; returns a job's exception if one
    failed.

    Pruned (a job set ``pruned_at_step``) -> PRUNED; NaN or an infinitely *good* score -> the
    worst finite score so far (a diverged configuration is bad, not an error); an infinitely
    *bad* score (``final/steps_to_threshold`` of a trial that never reached the threshold) is
    told as it is: Optuna ranks it below every finite score; an exception -> FAIL.
    """
    try:
        value = trial_value(results)  # re-raises what a job raised
    except Exception as e:
        study.tell(trial, state=TrialState.FAIL, skip_if_finished=True)
        log.warning("trial %d failed: %s", trial.number, e)
        return e
    (frozen,) = [t for t in study.get_trials(deepcopy=False) if t.number == trial.number]
    if frozen.state.is_finished():  # another sweeper failed it as stale meanwhile
        log.warning("trial %d was already told %s elsewhere", trial.number, frozen.state.name)
    elif PRUNED_AT in frozen.user_attrs:
        study.tell(trial, state=TrialState.PRUNED)
    elif value == infinitely_bad(study):
        log.warning("trial %d scored %s: ranked below every finite score", trial.number, value)
        study.tell(trial, value)
    elif not math.isfinite(value):
        worst = worst_finite(study)
        log.warning(
            "trial %d diverged (%s): scored %s, the worst so far", trial.number, value, worst
        )
        trial.set_user_attr("diverged", True)
        study.tell(trial, worst)
    else:
        study.tell(trial, value)
    return None


def trials_done(study: optuna.Study) -> int:
    """Trials that ended (complete, pruned, or failed and not retried)."""
    return len([t for t in counted_trials(study.get_trials(deepcopy=False)) if t.state in DONE])
