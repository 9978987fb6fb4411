"""Reference arms (``walkers.compare reference=[bundle]``): seeds from a bundle compared without
being rerun, on real tiny runs in two real stores, and the references that are not like for like
refused in one line."""

from __future__ import annotations

import gzip
import json
import shutil

import pytest
import yaml

from tests.conftest import all_runs, compose_cfg, new_store, one_line_error, run_cli
from walkers.analysis.comparison import build_comparison
from walkers.analysis.comparison import compare as compare_in_process
from walkers.errors import ConfigError
from walkers.export import export
from walkers.tracking import bundles
from walkers.tracking.client import get_or_create_experiment
from walkers.train import train as train_run

TINY = [
    "env=pendulum",
    "total_steps=600",
    "eval_every=200",
    "eval_episodes=2",
    "checkpoint_every=600",
    "progress=false",
    "tracking.experiment=ref",
    "algo.learning_starts=200",
    "algo.batch_size=32",
]


def train(store, algo: str) -> None:
    """Seeds 0 and 1 of ``algo``, in-process (the command line's runs are another module's)."""
    for seed in (0, 1):
        train_run(compose_cfg([f"algo={algo}", f"seed={seed}", *TINY, *store["overrides"]]))


def compare(store, *args: str, out: str = "report"):
    return run_cli(
        ["env=pendulum", "tracking.experiment=ref", f"out={store['path'] / out}",
         "log_report=false", *args, *store["overrides"]],
        cwd=store["path"],
        module="walkers.compare",
    )  # fmt: skip


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """TD3's seeds trained in one store and exported; SAC's trained in another."""
    theirs = new_store(tmp_path_factory.mktemp("theirs"))
    train(theirs, "td3")
    bundle = theirs["path"] / "td3_bundle"
    settings = ["tracking.experiment=ref", f"out={bundle}", f"tracking.uri={theirs['uri']}"]
    export(compose_cfg(settings, config_name="export"))
    ours = new_store(tmp_path_factory.mktemp("ours"))
    train(ours, "sac")
    return theirs, ours, bundle


def test_a_reference_arm_is_compared_without_being_rerun(stores):
    theirs, ours, bundle = stores
    result = compare(ours, f"reference=[{bundle}]")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "seeds: sac 2, td3 2" in result.stdout  # TD3 never ran in this store
    report = (ours["path"] / "report" / "report.md").read_text()
    assert "## Arms from references" in report
    assert f"| `{bundle}` | td3 | 2 | experiment 'ref'" in report
    # the reference arm's statistics are those of its own store's report, to the digit
    alone = theirs["path"] / "alone"
    compare_in_process(compose_cfg(
        ["env=pendulum", "tracking.experiment=ref", f"out={alone}", "log_report=false",
         *theirs["overrides"]],
        config_name="compare",
    ))  # fmt: skip
    here = json.loads((ours["path"] / "report" / "summary.json").read_text())["algos"]["td3"]
    there = json.loads((alone / "summary.json").read_text())["algos"]["td3"]
    assert here == there


def _edited(bundle, tmp_path, change) -> str:
    copy = tmp_path / "td3_bundle"
    shutil.copytree(bundle, copy)
    with gzip.open(copy / bundles.RUNS_FILE, "rt") as f:
        document = json.load(f)
    for record in document["runs"]:
        change(record)
    with gzip.open(copy / bundles.RUNS_FILE, "wt") as f:
        json.dump(document, f)
    return str(copy)


def test_a_reference_trained_by_another_update_is_refused_in_one_line(stores, tmp_path):
    _, ours, bundle = stores

    def other_update(record):
        record["fingerprint"] = [x * 1.1 + 0.01 for x in record["fingerprint"]]

    edited = _edited(bundle, tmp_path, other_update)
    line = one_line_error(compare(ours, f"reference=[{edited}]", out="refused"))
    assert "reference 'td3_bundle' is not like for like: run " in line
    assert "was trained by another update than today's td3 (number 0: " in line, line
    assert not (ours["path"] / "refused").exists()


def test_a_reference_from_before_a_hyperparameter_existed_is_checked_with_its_default(
    stores, tmp_path
):
    """A run made before ``algo.capture`` was declared has no such key in its config: today's
    update is built with the declared default, the behaviour the run had (a TD3 baseline of
    results/ was refused with a TypeError before)."""
    _, ours, bundle = stores

    def older(record):
        config = yaml.safe_load(record["config"])
        del config["algo"]["capture"]
        record["config"] = yaml.safe_dump(config)

    cfg = compose_cfg(
        [f"reference=[{_edited(bundle, tmp_path, older)}]", "env=pendulum",
         "tracking.experiment=ref", f"tracking.uri={ours['uri']}"],
        config_name="compare",
    )  # fmt: skip
    comparison, _ = build_comparison(cfg)
    assert {r.algo: len(r.runs) for r in comparison.algos} == {"sac": 2, "td3": 2}


def _set(section: str, key: str, value: str):
    def change(record):
        record[section][key] = value

    return change


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (_set("tags", "env", "Pendulum-v0"), "its runs are of Pendulum-v0, not Pendulum-v1"),
        (
            _set("params", "eval_episodes", "10"),
            "has eval_episodes=10, the runs it stands beside 2",
        ),
        (_set("params", "env.max_episode_steps", "100"), "has env.max_episode_steps=100, the"),
        (_set("params", "total_steps", "1200"), "has total_steps=1200, this comparison 600"),
        (_set("tags", "impl", "sb3"), "carries no update fingerprint"),
        (  # resumed under other code, in a bundle written before exports dropped its fingerprint
            _set("tags", "walkers.code_digest", "0lder+newer"),
            "was trained by 2 codes in turn (resumed under another: code digests 0lder then newer)",
        ),
    ],
)
def test_a_reference_that_is_not_like_for_like_is_refused(stores, tmp_path, change, expected):
    """The checks ``walkers.compare`` runs first (in-process: the CLI case above proves the
    line); a run without a fingerprint stands for one exported by other code than trained it."""
    _, ours, bundle = stores

    def edited(record):
        change(record)
        if "impl" in record["tags"] and record["tags"]["impl"] == "sb3":
            record["fingerprint"] = None

    cfg = compose_cfg(
        [f"reference=[{_edited(bundle, tmp_path, edited)}]", "env=pendulum",
         "tracking.experiment=ref", f"tracking.uri={ours['uri']}"],
        config_name="compare",
    )  # fmt: skip
    with pytest.raises(ConfigError) as refused:
        build_comparison(cfg)
    assert expected in str(refused.value)
    assert str(refused.value).startswith("reference 'td3_bundle' is not like for like")


def test_references_on_an_env_the_store_has_no_runs_of_are_held_to_each_other(stores, tmp_path):
    """With nothing of the store's on the env to stand beside, two references must still share
    the evaluation protocol and the budget: the first's settings hold the second."""
    _, _, bundle = stores
    empty = new_store(tmp_path / "empty")
    get_or_create_experiment(empty["client"], "ref")  # its runs, if any, are of other envs

    def more_episodes(record):
        record["params"]["eval_episodes"] = "10"

    other = tmp_path / "other_td3"
    shutil.copytree(_edited(bundle, tmp_path, more_episodes), other)
    cfg = compose_cfg(
        [f"reference=[{bundle},{other}]", "env=pendulum", "algos=[td3]",
         "tracking.experiment=ref", f"tracking.uri={empty['uri']}"],
        config_name="compare",
    )  # fmt: skip
    with pytest.raises(ConfigError) as refused:
        build_comparison(cfg)
    assert str(refused.value).startswith("reference 'other_td3' is not like for like: run ")
    assert "has eval_episodes=10, the runs it stands beside 2" in str(refused.value)


@pytest.mark.slow  # `make test-slow`: a run trained and continued on the command line
def test_a_run_continued_to_a_longer_budget_is_compared_at_the_budget_it_trained_for(
    stores, tmp_path
):
    """``resume=<id> total_steps=N`` cannot rewrite the run's ``total_steps`` param: the run says
    N in a tag, and a comparison, a budget check and a reference read N, not the param."""
    _, ours, _ = stores
    longer = new_store(tmp_path / "longer")
    train_run(compose_cfg(["algo=td3", "seed=0", *TINY, *longer["overrides"]]))
    (run,) = all_runs(longer["client"])
    resumed = run_cli([f"resume={run.info.run_id}", "total_steps=800", *longer["overrides"]],
                      cwd=longer["path"])  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    run = longer["client"].get_run(run.info.run_id)
    assert run.info.status == "FINISHED"
    assert run.data.params["total_steps"] == "600" and run.data.tags["walkers.total_steps"] == "800"
    at = compose_cfg(["env=pendulum", "tracking.experiment=ref", f"tracking.uri={longer['uri']}"],
                     config_name="compare")  # fmt: skip
    comparison, _ = build_comparison(at)
    assert comparison.budgets == {"env_steps": 800}
    # exported, it is refused beside runs of 600 steps
    bundle = tmp_path / "longer_td3"
    export(compose_cfg(["tracking.experiment=ref", f"out={bundle}",
                        f"tracking.uri={longer['uri']}"], config_name="export"))  # fmt: skip
    cfg = compose_cfg([f"reference=[{bundle}]", "env=pendulum", "tracking.experiment=ref",
                       f"tracking.uri={ours['uri']}"], config_name="compare")  # fmt: skip
    with pytest.raises(ConfigError) as refused:
        build_comparison(cfg)
    assert "has total_steps=800, this comparison 600" in str(refused.value)
