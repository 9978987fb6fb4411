"""Everything walkers does with MLflow: the store and a run's own logging
(:mod:`~walkers.tracking.client`: connecting, queries, filters,
:class:`~walkers.tracking.client.Tracker`, :func:`~walkers.tracking.client.ending`), the names
of statuses, tags and axes (:mod:`~walkers.tracking.names`), bundles of runs
(:mod:`~walkers.tracking.bundles`), the Hydra callbacks (:mod:`~walkers.tracking.hydra_callbacks`)
and the servers a team runs (:mod:`~walkers.tracking.servers`). Import each name from its module:
``names`` imports no MLflow, so a command that only names tags and statuses (a refused typo,
``--help``) starts without it.
"""
