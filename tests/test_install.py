"""An installed walkers (``pip install .``, no checkout) finds its configs and studies.

A cluster worker or a user who installs the package has no repository: conf/ and sweeps/ ship
inside the package. The package is installed (without its dependencies, which this environment
has) into a temporary folder and run from another working directory.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from tests.conftest import PROJECT_ROOT, all_runs, new_store


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """walkers installed into a folder of its own, built from a copy of the sources (a build
    leaves build/ and *.egg-info beside the sources it builds)."""
    source, target = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("site")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(PROJECT_ROOT / name, source / name)
    for name in ("walkers", "conf", "sweeps"):
        shutil.copytree(
            PROJECT_ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__")
        )
    build = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation"]
        + ["--target", str(target), str(source)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    # a quiet install: every config folder is declared, so setuptools has nothing to warn of
    assert "Warning" not in build.stdout + build.stderr, (build.stdout + build.stderr)[-3000:]
    return target


def run_installed(target, args: list[str], cwd) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(target)}
    env.pop("MLFLOW_TRACKING_URI", None)
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


def test_the_installed_package_carries_its_configs_and_studies(installed, tmp_path):
    where = run_installed(
        installed, ["-c", "import walkers; print(walkers.__file__, walkers.CONF_DIR)"], tmp_path
    )
    module, conf_dir = where.stdout.split()
    assert module.startswith(str(installed)) and conf_dir.startswith(str(installed))
    job = run_installed(
        installed, ["-m", "walkers.train", "--cfg", "job", "env=pendulum"], tmp_path
    )
    assert job.returncode == 0 and "Pendulum-v1" in job.stdout, job.stderr[-2000:]
    study = run_installed(
        installed, ["-m", "walkers.train", "--cfg", "job", "sweeps=pendulum_tiny"], tmp_path
    )
    assert study.returncode == 0 and "total_steps" in study.stdout, study.stderr[-2000:]
    help_ = run_installed(installed, ["-m", "walkers.train", "--help"], tmp_path)
    assert help_.returncode == 0, help_.stderr[-2000:]
    assert "pendulum_tiny" in help_.stdout and "ppo_value_clip" in help_.stdout  # sweeps/, conf/ab/


def test_the_installed_package_trains_from_another_directory(
    installed, tmp_path, _empty_store_file
):
    store = new_store(tmp_path, _empty_store_file)
    args = ["-m", "walkers.train", "algo=reinforce", "env=pendulum", "total_steps=400"]
    args += ["eval_every=200", "eval_episodes=1", "progress=false", *store["overrides"]]
    result = run_installed(installed, args, tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED" and "final/return_mean" in run.data.metrics
