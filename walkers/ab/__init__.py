"""A/B studies: a suite of envs, seeds in rounds until each question is answered, and a rerun
that picks up where the last one stopped.

    python -m walkers.train -m ab=tiny                      # conf/ab/tiny.yaml, to its verdict
    python -m walkers.train -m ab=locomotion hydra/launcher=joblib

- :mod:`walkers.ab.spec`: a study file's declaration (arms, envs, seeds, score, alpha, delta),
  checked in one line; its questions, design and job keys;
- :mod:`walkers.ab.ledger`: the study's MLflow run and the scores of its finished jobs;
- :mod:`walkers.ab.rounds`: from the scores, each question's answer and the seeds still needed;
- :mod:`walkers.ab.study_sweeper`: the Hydra sweeper that launches the rounds over any launcher.

The test itself is :mod:`walkers.analysis.sequential`.
"""
