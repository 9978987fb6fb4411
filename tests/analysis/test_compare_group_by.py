"""Two configurations of one algorithm: two arms, never pooled; a ``group_by`` study of them."""

from __future__ import annotations

import json

import pytest

from tests.conftest import TINY, all_runs, compose_cfg, new_store, run_cli
from walkers.analysis.comparison import compare
from walkers.errors import ConfigError
from walkers.train import train

SIZES = ["[16, 16]", "[32, 32]"]  # as the runs' params spell them
SEEDS = [0, 1]


@pytest.fixture(scope="module")
def sizes_store(tmp_path_factory, _empty_store_file):
    """TD3 on Pendulum with hidden sizes [16,16] and [32,32], 2 seeds each (tiny, in-process).

    The two seeds of a size also differ in keys that cannot change results (logging cadence),
    which must not split them.
    """
    path = tmp_path_factory.mktemp("sizes")
    store = new_store(path, _empty_store_file)
    for size in SIZES:
        for seed in SEEDS:
            overrides = [
                "env=pendulum",
                "algo=td3",
                f"algo.hidden_sizes={size.replace(' ', '')}",
                "algo.learning_starts=200",  # a few hundred updates: the sizes learn differently
                "algo.batch_size=32",
                f"seed={seed}",
                "torch_threads=1",
                "tracking.experiment=sizes",
                *TINY,
                f"log_every={100 * (seed + 1)}",
                *store["overrides"],
            ]
            train(compose_cfg(overrides))
    return store


def compare_overrides(store, out, *extra) -> list[str]:
    return [
        *store["overrides"],
        "tracking.experiment=sizes",
        "env=pendulum",
        f"out={out}",
        "n_resamples=200",
        *extra,
    ]


def _runs_of_size(store, size: str) -> set[str]:
    return {
        r.info.run_id
        for r in all_runs(store["client"])
        if r.data.params.get("algo.hidden_sizes") == size
    }


def test_two_configurations_of_one_algorithm_are_two_arms(sizes_store, tmp_path):
    comparison, out, _ = compare(
        compose_cfg(compare_overrides(sizes_store, tmp_path, "algos=[td3]", "log_report=false"),
                    config_name="compare")
    )  # fmt: skip
    names = [f"td3 (algo.hidden_sizes={size})" for size in SIZES]
    assert [a.algo for a in comparison.algos] == names
    for arm, size in zip(comparison.algos, SIZES, strict=True):
        # every seed of the arm, and only runs of its configuration
        assert {r.run_id for r in arm.runs} == _runs_of_size(sizes_store, size)
        assert len(arm.runs) == len(SEEDS)
    assert {(p.a, p.b) for p in comparison.pairs} == {tuple(names)}

    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["algos"]) == names
    assert summary["algos"][names[0]]["differs_in"] == {"algo.hidden_sizes": SIZES[0]}
    (split,) = summary["split"]
    assert split.startswith("td3: 2 configurations") and "differ in algo.hidden_sizes" in split
    report = (out / "report.md").read_text()
    assert "## Arms" in report and f"- {split}" in report
    assert f"| {names[0]} | 2 |" in report  # the per-arm table


def test_group_by_study_as_a_user_runs_it(sizes_store, tmp_path):
    result = run_cli(
        compare_overrides(sizes_store, tmp_path, "group_by=algo.hidden_sizes"),
        cwd=sizes_store["path"],
        module="walkers.compare",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    arms = [f"algo.hidden_sizes={size}" for size in SIZES]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["group_by"] == ["algo.hidden_sizes"] and summary["split"] == []
    assert list(summary["algos"]) == arms
    for arm, size in zip(arms, SIZES, strict=True):
        assert set(summary["algos"][arm]["run_ids"]) == _runs_of_size(sizes_store, size)
        assert summary["algos"][arm]["group"] == {"algo.hidden_sizes": size}
    assert [(p["a"], p["b"], p["quantity"]) for p in summary["pairs"]] == [
        (*arms, "score"),
        (*arms, "auc"),
    ]
    report = (tmp_path / "report.md").read_text()
    assert report.startswith("# td3 on Pendulum-v1 by algo.hidden_sizes")
    assert f"| {arms[0]} vs {arms[1]} | final return |" in report  # the pairwise table
    assert "![score by algo.hidden_sizes](group_by.png)" in report
    assert (tmp_path / "group_by.png").read_bytes()[:4] == b"\x89PNG"
    assert "Published reference figures" not in report  # none for Pendulum
    assert f"{arms[0]} vs {arms[1]}:" in result.stdout  # the verdict, printed


def test_a_group_by_key_no_run_has_is_a_one_line_error(sizes_store, tmp_path):
    """In-process: test_compare.py's command-line refusal proves the line and the exit."""
    out = tmp_path / "report"
    cfg = compose_cfg(
        compare_overrides(sizes_store, out, "group_by=algo.hiden_sizes"), config_name="compare"
    )
    with pytest.raises(ConfigError) as refused:
        compare(cfg)
    error = str(refused.value)
    assert "group_by='algo.hiden_sizes'" in error and "did you mean 'algo.hidden_sizes'" in error
    assert "\n" not in error and not out.exists()
