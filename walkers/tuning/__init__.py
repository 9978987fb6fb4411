"""Parameter tuning: the Optuna sweeper (the study side), the trial reporter (the job side) and
the export of a study's best trial as a preset."""
