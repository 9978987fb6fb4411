"""A plain multirun (`-m`, walkers' stand-in for Hydra's basic sweeper) opens its store before
its jobs: four jobs launched together into a new sqlite store each ran MLflow's migrations, and
three of four died of it ("duplicate column name: step")."""

from __future__ import annotations

import pytest
from mlflow import MlflowClient

from tests.conftest import TINY, all_runs, one_line_error, run_cli

JOBS = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=4", "algo=reinforce", "env=pendulum"]


@pytest.mark.slow  # `make test-slow`: four jobs racing to create one sqlite store
def test_jobs_launched_together_into_a_new_sqlite_store_all_finish(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"  # a store nobody has opened yet

    done = run_cli([*JOBS, "seed=0,1,2,3", *TINY, f"tracking.uri={uri}"], cwd=tmp_path)

    assert done.returncode == 0, done.stderr[-3000:]
    runs = all_runs(MlflowClient(uri))
    assert sorted(r.data.tags["seed"] for r in runs) == ["0", "1", "2", "3"]
    assert {r.info.status for r in runs} == {"FINISHED"}


@pytest.mark.slow  # MLflow itself retries an unopenable sqlite file for about 100 s first
def test_an_unusable_store_is_one_line_before_any_job(tmp_path):
    bad = tmp_path / "a_file"
    bad.write_text("not a folder")

    done = run_cli(
        [*JOBS, "seed=0,1", *TINY, f"tracking.uri=sqlite:///{bad}/mlflow.db"], cwd=tmp_path
    )

    assert "tracking.uri=" in one_line_error(done)
    assert "Launching" not in done.stdout + done.stderr  # no job started
