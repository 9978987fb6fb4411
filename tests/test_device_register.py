"""benchmarks/device_register.py, which registers the checkout on the lent GPU's Python as an
editable install would: Hydra finds walkers' sweepers there through the registered entry points
(without them a multirun there stopped at "Unknown plugin class")."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from importlib.metadata import distributions

from tests.conftest import PROJECT_ROOT


def register_into(site) -> subprocess.CompletedProcess:
    """The script as device_venv.sh runs it, with the site folder it writes into made ``site``."""
    code = (
        "import pathlib, runpy, sys, sysconfig; "
        "sysconfig.get_paths = lambda: {'purelib': sys.argv[1]}; "
        "runpy.run_path('benchmarks/device_register.py', run_name='__main__')"
    )
    return subprocess.run(
        [sys.executable, "-c", code, str(site)], cwd=PROJECT_ROOT, capture_output=True, text=True
    )


def test_the_checkout_is_registered_with_pyprojects_entry_points_and_a_second_run_replaces_it(
    tmp_path,
):
    project = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["project"]
    declared = project["entry-points"]["hydra.plugins"]

    for _ in range(2):  # device_venv.sh may run twice on one machine
        done = register_into(tmp_path)
        assert done.returncode == 0, done.stderr

    [dist] = list(distributions(path=[str(tmp_path)]))
    assert (dist.metadata["Name"], dist.version) == ("walkers", project["version"])
    found = {e.name: e.value for e in dist.entry_points if e.group == "hydra.plugins"}
    assert found == declared
    assert (tmp_path / "__editable__.walkers.pth").read_text().strip() == str(PROJECT_ROOT)
    assert len(list(tmp_path.glob("walkers-*.dist-info"))) == 1
