"""A training run's lifecycle (walkers/training/run.py): opened, reopened on resume, ended with
a status that says what can be done with it, even when opening itself fails."""

from __future__ import annotations

import shutil

import pytest

from tests.conftest import TINY, all_runs, compose_cfg, new_store, run_cli
from walkers.train import train

pytestmark = pytest.mark.faults  # `make test-faults`, beside `make test` in CI


def test_a_resume_that_fails_to_reopen_its_run_leaves_it_continuable(tmp_path):
    """The resumed run's folder cannot take its config.yaml (a directory stands in the way): the
    resume fails, the run ends KILLED, not FAILED (it can still go on), and once the way is clear
    the same command continues it."""
    store = new_store(tmp_path)
    train(compose_cfg(["algo=td3", "env=pendulum", *TINY, "algo.learning_starts=100",
                       *store["overrides"]]))  # fmt: skip
    (run,) = all_runs(store["client"])
    run_id = run.info.run_id
    config_yaml = tmp_path / "work" / "runs" / run_id / "config.yaml"
    config_yaml.unlink()
    config_yaml.mkdir()  # the fault
    resume = [f"resume={run_id}", "total_steps=900", *store["overrides"]]
    failed = run_cli(resume, cwd=tmp_path)
    assert failed.returncode != 0
    assert "IsADirectoryError" in failed.stderr
    assert store["client"].get_run(run_id).info.status == "KILLED"
    shutil.rmtree(config_yaml)
    result = run_cli(resume, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert store["client"].get_run(run_id).info.status == "FINISHED"
    steps = [m.step for m in store["client"].get_metric_history(run_id, "eval/return_mean")]
    assert steps == [300, 600, 900] and len(all_runs(store["client"])) == 1
