"""`make dashboard`: optuna-dashboard on the sweeps' study storage, served by walkers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request

import optuna

from tests.cluster_kit import free_port
from tests.conftest import one_line_error, run_cli


def test_the_dashboard_serves_the_studies_of_the_sweeps_storage(tmp_path):
    study = optuna.create_study(study_name="shown", storage=f"sqlite:///{tmp_path / 'optuna.db'}")
    study.optimize(lambda trial: trial.suggest_float("x", 0, 1), n_trials=2)
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "walkers.dashboard", f"port={port}"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/studies", timeout=5) as r:
                    studies = json.load(r)["study_summaries"]
                break
            except OSError:
                assert proc.poll() is None, proc.communicate()[1][-2000:]
                assert time.monotonic() < deadline
                time.sleep(0.5)
    finally:
        proc.terminate()
        _, stderr = proc.communicate(timeout=30)
    assert [s["study_name"] for s in studies] == ["shown"]
    assert f"http://127.0.0.1:{port}" in stderr
    assert sorted(os.listdir(tmp_path)) == ["optuna.db"]  # no log file, no outputs/


def test_no_study_storage_yet_is_one_line_and_creates_nothing(tmp_path):
    line = one_line_error(run_cli([], cwd=tmp_path, module="walkers.dashboard"))
    assert "has no studies yet (no such file)" in line
    assert os.listdir(tmp_path) == []
