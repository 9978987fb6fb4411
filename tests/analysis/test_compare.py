"""A/B comparison: runs launched in parallel into a fresh store, then the report."""

from __future__ import annotations

import json
import os
from types import SimpleNamespace

import numpy as np
import pytest

from tests.conftest import TINY, all_runs, compose_cfg, new_store, one_line_error, run_cli
from walkers.analysis.comparison import compare
from walkers.analysis.comparison_data import SeedRun
from walkers.analysis.pairwise import compare_groups
from walkers.analysis.report import verdict
from walkers.analysis.selection import resolve_dataset
from walkers.errors import ConfigError

ALGOS = ["reinforce", "td3"]


@pytest.fixture(scope="module")
def ab_store(tmp_path_factory, _empty_store_file):
    """2 algorithms x 2 seeds launched as one multirun, two jobs at once, on a fresh store.

    Also: a run on another env and one still RUNNING, which the comparison must leave out.
    """
    store = new_store(tmp_path_factory.mktemp("ab"))
    result = run_cli(
        [
            "-m",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
            "torch_threads=null",  # all cores, shared out among the parallel jobs
            f"algo={','.join(ALGOS)}",
            "seed=0,1",
            "env=pendulum",
            "tracking.experiment=ab",
            *TINY,
            *store["overrides"],
        ],
        cwd=store["path"],
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    client = store["client"]
    experiment_id = client.get_experiment_by_name("ab").experiment_id
    for env, status in (("Hopper-v5", "FINISHED"), ("Pendulum-v1", "RUNNING")):
        run = client.create_run(experiment_id, tags={"algo": "td3", "env": env, "seed": "9"})
        client.log_param(run.info.run_id, "total_steps", "600")
        client.log_metric(run.info.run_id, "eval/return_mean", -100.0, step=600)
        if status == "FINISHED":
            client.set_terminated(run.info.run_id, status)
    return store


def compare_cfg(store, tmp_path, *overrides):
    return compose_cfg(
        [
            *store["overrides"],
            "tracking.experiment=ab",
            "env=pendulum",
            f"algos=[{','.join(ALGOS)}]",
            f"out={tmp_path}",
            "n_resamples=500",
            *overrides,
        ],
        config_name="compare",
    )


def test_parallel_jobs_all_finish_sharing_the_cores(ab_store):
    runs = [r for r in all_runs(ab_store["client"]) if r.data.tags["seed"] != "9"]
    assert sorted((r.data.tags["algo"], r.data.tags["seed"]) for r in runs) == [
        ("reinforce", "0"),
        ("reinforce", "1"),
        ("td3", "0"),
        ("td3", "1"),
    ]
    assert {r.info.status for r in runs} == {"FINISHED"}
    # each of the 2 parallel jobs gets its share of this machine's cores, at least one
    threads = max(1, (os.cpu_count() or 1) // 2)
    assert {r.data.params["torch_threads"] for r in runs} == {str(threads)}


def test_compare_reports_every_seed_and_leaves_out_the_rest(ab_store, tmp_path):
    comparison, out, url = compare(compare_cfg(ab_store, tmp_path))
    client = ab_store["client"]
    summary = json.loads((out / "summary.json").read_text())
    for algo in ALGOS:
        runs = [
            r
            for r in all_runs(client)
            if r.data.tags.get("algo") == algo and r.data.tags.get("seed") in ("0", "1")
        ]
        assert sorted(summary["algos"][algo]["run_ids"]) == sorted(r.info.run_id for r in runs)
        # the per-seed scores are the runs' own logged final metrics
        logged = sorted(r.data.metrics["final/return_mean"] for r in runs)
        result = next(a for a in comparison.algos if a.algo == algo)
        np.testing.assert_allclose(sorted(result.scores), logged)
        assert summary["algos"][algo]["score_mean"] == pytest.approx(np.mean(logged))
        spent = sum(r.data.metrics["final/cpu_hours"] for r in runs)  # each run's own count
        assert spent > 0 and summary["algos"][algo]["cpu_hours"] == pytest.approx(spent)
        assert summary["algos"][algo]["cpu_hours_runs"] == len(runs)
    assert [p["quantity"] for p in summary["pairs"]] == ["score", "auc"]
    left_out = " ".join(summary["left_out"])
    assert "Hopper-v5: 1" in left_out and "RUNNING" in left_out

    report = (out / "report.md").read_text()
    assert "reinforce vs td3 on Pendulum-v1" in report
    better, worse = sorted(comparison.algos, key=lambda a: -a.iqm[0])  # the verdict's orientation
    assert f"P({better.algo} > {worse.algo})" in report
    assert "## Left out" in report
    assert "## Arms" not in report and summary["split"] == []  # one configuration per algorithm
    for png in ("learning_curves.png", "scores.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"

    (report_run,) = [r for r in all_runs(client) if r.data.tags.get("walkers.kind") == "report"]
    assert report_run.info.status == "FINISHED" and report_run.info.run_id in url
    logged_files = {a.path for a in client.list_artifacts(report_run.info.run_id)}
    assert {"report.md", "summary.json", "learning_curves.png", "scores.png"} <= logged_files
    # a second report does not count the first one as a training run
    again, _, _ = compare(compare_cfg(ab_store, tmp_path / "again", "log_report=false"))
    assert [len(a.runs) for a in again.algos] == [2, 2]


def test_compare_cli_names_missing_algorithm(ab_store, tmp_path):
    result = run_cli(
        [
            *ab_store["overrides"],
            "tracking.experiment=ab",
            "env=pendulum",
            "algos=[td3,sac]",
            f"out={tmp_path}",
        ],
        cwd=ab_store["path"],
        module="walkers.compare",
    )
    error = one_line_error(result)
    assert "sac" in error and "reinforce, td3" in error


def _synthetic(algo: str, finals: list[float]) -> list[SeedRun]:
    steps = np.array([100, 200])
    return [
        SeedRun(
            f"{algo}{i}",
            algo,
            str(i),
            steps,
            np.array([0.0, f]),
            {
                "final/return_mean": f,
                "final/auc": f / 2,
                "final/steps_to_threshold": 200.0 if f >= 50 else np.inf,
            },
        )
        for i, f in enumerate(finals)
    ]


def test_verdict_follows_the_evidence():
    def run(a_finals, b_finals):
        grouped = {
            "td3": _synthetic("td3", a_finals),
            "reinforce": _synthetic("reinforce", b_finals),
        }
        return verdict(
            compare_groups(
                grouped,
                ["td3", "reinforce"],
                env_id="E",
                threshold=50,
                budgets={"env_steps": 200},
                score="final/return_mean",
                n_resamples=500,
            )
        )

    clear = run([90, 95, 100, 105, 110], [1, 2, 3, 4, 5])
    assert "td3 vs reinforce: td3 learns better (final return: P(td3 > reinforce) = 1" in clear
    assert "; td3 learns faster (AUC" in clear
    assert "td3 5/5, reinforce 0/5" in clear
    reversed_ = run([1, 2, 3, 4, 5], [90, 95, 100, 105, 110])  # named the other way round
    assert "reinforce vs td3: reinforce learns better" in reversed_
    overlapping = run([1, 3, 5, 7, 9], [2, 4, 6, 8, 10])
    assert "no reliable difference in final return" in overlapping
    # Perfect separation with 3 seeds each is not enough: the smallest Mann-Whitney p is 0.1
    few = run([90, 95, 100], [1, 2, 3])
    assert "no reliable difference in final return" in few
    assert "smallest possible p is 0.1" in few
    assert "(95% CIs)." in few
    # One seed per arm has no CI: the ranking says so per arm and claims no CIs
    single = run([100], [1])
    assert "td3 100 (too few seeds for a CI), reinforce 1 (too few seeds for a CI)." in single
    assert "CIs)" not in single


def test_a_dataset_named_without_its_version_is_found_when_one_version_has_runs():
    """``dataset=`` of a report: the exact id, or the id without ``-v<N>`` when runs learned
    from one version of it; several versions or none are one-line errors naming what is there."""

    def offline(dataset: str):  # what comparable_runs reads of an MLflow run
        tags = {"dataset": dataset, "walkers.x_axis": "gradient_steps"}
        return SimpleNamespace(data=SimpleNamespace(tags=tags))

    runs = [offline("a/medium-v0"), offline("a/medium-v0"), offline("a/expert-v0"),
            offline("a/expert-v1")]  # fmt: skip
    assert resolve_dataset(None, runs, "E") == "a/medium-v0"  # the most common
    assert (
        resolve_dataset("a/medium", runs, "E")
        == resolve_dataset("a/medium-v0", runs, "E")
        == "a/medium-v0"
    )
    assert resolve_dataset("a/expert-v1", runs, "E") == "a/expert-v1"
    with pytest.raises(ConfigError, match=r"several versions of it \(a/expert-v0, a/expert-v1\)"):
        resolve_dataset("a/expert", runs, "E")
    with pytest.raises(
        ConfigError,
        match=r"^dataset='a/medum' is not allowed: no finished offline run of E learned from it; "
        r"datasets they learned from: a/expert-v0, a/expert-v1, a/medium-v0$",
    ):
        resolve_dataset("a/medum", runs, "E")
