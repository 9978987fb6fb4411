"""benchmarks/device_baselines.sh, the results call of a lent GPU, tried on the CPU: it takes the
pairs whose page results/ lacks, trains each as one population, and brings home, in one archive
(a call brings back at most 8 files, none deeper than 2 folders), a page that `walkers.results`
can read for each population that finished, and none for one its deadline stopped, but how far it
got."""

from __future__ import annotations

import tarfile

import pytest
import yaml

from tests.conftest import run_device_script
from walkers.tracking import bundles

#: Two tiny populations in bash: end to end, so `make test-slow` (CI runs it after `make test`).
pytestmark = pytest.mark.slow

TINY = "eval_every=500 eval_episodes=2 algo.learning_starts=200 algo.batch_size=32"


def run_script(tmp_path, pairs: str, steps: int = 1000, deadline: int = 400):
    return run_device_script(
        "device_baselines.sh",
        tmp_path,
        RESULTS=str(tmp_path / "results"),
        PAIRS=pairs,
        JOBS="2",
        STEPS=str(steps),
        DEADLINE=str(deadline),
        EXTRA=TINY,
    )


def test_the_pairs_results_lacks_come_home_as_pages_walkers_results_reads(tmp_path):
    (tmp_path / "results" / "td3_hopper_1k").mkdir(parents=True)
    (tmp_path / "results" / "td3_hopper_1k" / "page.yaml").write_text("title: there already\n")

    done = run_script(tmp_path, "td3:hopper td3:pendulum")

    assert done.returncode == 0, done.stdout + done.stderr
    assert "device_baselines: td3:pendulum on CPU" in done.stdout  # td3:hopper has its page
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == ["logs.tar.gz", "results.tar.gz", "summary.txt"]
    with tarfile.open(out / "results.tar.gz") as archive:
        archive.extractall(tmp_path / "home", filter="data")
    homes = sorted(p.name for p in (tmp_path / "home" / "results").iterdir())
    assert homes == ["td3_pendulum_1k"]
    home = tmp_path / "home" / "results" / "td3_pendulum_1k"
    page = yaml.safe_load((home / "page.yaml").read_text())
    assert {"title", "budget", "machine", "command", "commit", "date", "compare"} <= set(page)
    assert page["compare"] == ["env=pendulum"]
    assert TINY in page["title"] and TINY in page["command"]  # not "walkers' defaults" alone
    runs = bundles.read_bundle(home / "bundle")["runs"]
    assert sorted(r["tags"]["walkers.job_key"] for r in runs) == [
        f"baseline/td3/Pendulum-v1/{seed}" for seed in range(3)
    ]
    assert {r["status"] for r in runs} == {"FINISHED"}


def test_a_population_its_deadline_stops_brings_no_page_and_the_call_still_ends(tmp_path):
    done = run_script(tmp_path, "td3:pendulum", steps=100_000, deadline=8)  # far from done

    assert done.returncode == 0, done.stdout + done.stderr
    assert "td3_pendulum_100k: stopped at the deadline" in done.stdout  # SIGINT, then KILLED
    assert "of 100000 steps" in done.stdout  # how far it got: the next call's sizing
    assert "td3_pendulum_100k: nothing finished" in done.stdout
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == ["logs.tar.gz", "summary.txt"]  # no pages
    with tarfile.open(out / "logs.tar.gz") as archive:
        assert archive.getnames() == ["./td3_pendulum_100k.log"]
