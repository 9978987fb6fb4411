"""The few places walkers reaches past Optuna's public API, in one module.

Written against ``optuna==5.0.0`` (the version pinned in pyproject.toml); each helper says what
it relies on, so an Optuna upgrade checks this file and nothing else.

- :func:`stored_trial`: the stored (frozen) state of a live ``optuna.Trial`` without reading
  every trial of the study: ``study._storage.get_trial(trial._trial_id)``. The public
  ``study.get_trials()`` would fetch them all on every call.
- :func:`trial_id` / :func:`trial_by_id`: a trial's storage id (``trial._trial_id``), for
  heartbeats and for re-opening a trial a job was handed by id
  (``optuna.trial.Trial(study, trial_id)``, a constructor Optuna documents as internal).
"""

from __future__ import annotations

import optuna


def trial_id(trial: optuna.Trial) -> int:
    """The trial's id in its storage (``Trial._trial_id``)."""
    return trial._trial_id


def stored_trial(study: optuna.Study, trial: optuna.Trial) -> optuna.trial.FrozenTrial:
    """What the storage holds of ``trial`` now (its state, params, user attributes, value)."""
    return study._storage.get_trial(trial._trial_id)


def trial_by_id(study: optuna.Study, trial_id_: int) -> optuna.Trial:
    """A live handle on trial ``trial_id_`` of ``study`` (a job's trial, given by its id)."""
    return optuna.trial.Trial(study, trial_id_)
