"""The job side of an Optuna sweep: report evaluations to the trial, stop when it is pruned.

The sweeper (:mod:`walkers.tuning.optuna_sweeper`) passes each job its study, storage and trial
id as
``trial.*`` overrides; the pruner is the job's own ``pruner`` config (an ``optuna.pruners``
class, from ``conf/pruner/``), so a sweep file chooses it and a command line can swap it.

Pruners judge intermediate values in the study's direction, and the value reported is the eval
return (higher is better). A study that minimizes its metric (``final/steps_to_threshold``)
is therefore told the negated eval return, and a threshold pruner's bounds, written as eval
returns, are negated to match: a pruner config means the same in every study.
"""

from __future__ import annotations

import logging
import math

import optuna
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError
from optuna.exceptions import StorageInternalError
from optuna.study import StudyDirection
from sqlalchemy.exc import SQLAlchemyError

from walkers.errors import ConfigError
from walkers.tuning.optuna_internals import stored_trial, trial_by_id, trial_id
from walkers.tuning.studies import STORAGE_ENV, open_storage

log = logging.getLogger("walkers")

#: Trial user attribute the sweeper reads to tell the trial PRUNED.
PRUNED_AT = "pruned_at_step"
PRUNER_TARGETS = ["optuna.pruners.*"]
THRESHOLD_PRUNER = "optuna.pruners.ThresholdPruner"


def make_pruner(pruner_cfg: DictConfig | None, maximize: bool = True) -> optuna.pruners.BasePruner:
    """The pruner of ``pruner_cfg``; ``maximize=False``: for a study told negated eval returns."""
    if not pruner_cfg:
        return optuna.pruners.NopPruner()
    kwargs = OmegaConf.to_container(pruner_cfg, resolve=True)
    if not maximize and kwargs.get("_target_") == THRESHOLD_PRUNER:
        # "prune below eval return L" is "prune above -L" for the negated return
        lower, upper = kwargs.pop("lower", None), kwargs.pop("upper", None)
        kwargs["lower"] = None if upper is None else -upper
        kwargs["upper"] = None if lower is None else -lower
    return instantiate(kwargs, _execution_whitelist_=PRUNER_TARGETS)


def _storage(trial_cfg: DictConfig) -> str:
    """The study's storage URL; one with a password arrives as a reference to this machine's
    environment (:func:`walkers.tuning.studies.job_storage`)."""
    try:
        return trial_cfg.storage
    except InterpolationResolutionError:
        raise ConfigError(
            f"trial.storage is {STORAGE_ENV}, which this machine's environment does not have: "
            f"export {STORAGE_ENV} on every node (before `ray start`) as on the sweeper's"
        ) from None


class TrialReporter:
    """``reporter(step, eval_return) -> True`` when the trial should stop (it was pruned).

    A trial on several seeds (``seeds_per_trial``) runs one job per seed, possibly on different
    machines. Each job records its evaluation as a trial user attribute
    (``walkers.eval.<step>.<seed>``); the job that completes a step's set reports their mean to
    the pruner, and a pruning verdict (``pruned_at_step``) stops every seed's job at its next
    evaluation. No job waits for another.
    """

    def __init__(
        self, trial_cfg: DictConfig, pruner_cfg: DictConfig | None, seed: int = 0, seeds: int = 1
    ):
        storage = open_storage(_storage(trial_cfg), None, None, None)
        study = optuna.load_study(study_name=trial_cfg.study, storage=storage)
        maximize = study.direction == StudyDirection.MAXIMIZE
        study.pruner = make_pruner(pruner_cfg, maximize)
        #: +1, or -1 in a minimizing study: the sign of the eval return as the pruner sees it
        self.sign = 1.0 if maximize else -1.0
        self.trial = trial_by_id(study, trial_cfg.id)
        self.seed, self.seeds = seed, seeds
        self.pruned_at: int | None = None

    def __call__(self, step: int, value: float) -> bool:
        try:
            if self.seeds > 1:
                return self._seed_evaluation(step, value)
            if not math.isfinite(value):  # a diverged policy: nothing to compare; let it run out
                return False
            return self._report(step, value)
        except (SQLAlchemyError, StorageInternalError) as e:  # the study's database is down
            # (restarting): train on; the pruner misses this evaluation
            log.warning("evaluation at step %d not reported to the study: %s", step,
                        str(e).splitlines()[0])  # fmt: skip
            return False

    def _report(self, step: int, value: float) -> bool:
        self.trial.report(self.sign * value, step)
        if self.trial.should_prune():
            self.trial.set_user_attr(PRUNED_AT, step)
            self.pruned_at = step
            log.info(
                "trial %d pruned at step %d (eval return %.1f)", self.trial.number, step, value
            )
            return True
        return False

    def _seed_evaluation(self, step: int, value: float) -> bool:
        self.trial.set_user_attr(f"walkers.eval.{step}.{self.seed}", value)
        attrs = stored_trial(self.trial.study, self.trial).user_attrs
        if PRUNED_AT in attrs:  # another seed's job completed a set and the pruner said stop
            self.pruned_at = step
            log.info("trial %d pruned (at step %d): seed %d stops", self.trial.number,
                     attrs[PRUNED_AT], self.seed)  # fmt: skip
            return True
        values = [v for k, v in attrs.items() if k.startswith(f"walkers.eval.{step}.")]
        if len(values) < self.seeds:
            return False  # the other seeds have not evaluated this step yet
        mean = sum(values) / len(values)
        # a fresh view of the trial: the other seeds' jobs have reported steps since it was read
        self.trial = trial_by_id(self.trial.study, trial_id(self.trial))
        return math.isfinite(mean) and self._report(step, mean)
