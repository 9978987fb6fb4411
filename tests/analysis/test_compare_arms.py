"""Arms: which runs are seeds of one configuration, how arms are named, ordered and split."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from mlflow.entities import Param, Run, RunData, RunInfo, RunTag
from mlflow.utils.validation import validate_param_and_metric_name
from omegaconf import OmegaConf

from tests.conftest import compose_cfg
from walkers.analysis import arms
from walkers.analysis.comparison import mlflow_key
from walkers.analysis.comparison_data import SeedRun
from walkers.analysis.pairwise import compare_groups
from walkers.analysis.report import PUBLISHED_CAVEAT, markdown
from walkers.analysis.selection import published_figures
from walkers.cli import group_by_as_list
from walkers.tracking.client import get_or_create_experiment

TD3 = {
    "algo._target_": "walkers.agents.td3.TD3",
    "algo.name": "td3",
    "algo.hidden_sizes": "[256, 256]",
    "algo.lr": "0.0003",
    "env.id": "Pendulum-v1",
    "total_steps": "600",
}


def mlflow_run(run_id: str, algo: str = "td3", **params: str) -> Run:
    """An MLflow run entity as ``search_runs`` returns it: the config as params, the algo tag."""
    info = RunInfo(run_id, "0", "user", "FINISHED", 0, 1, "active")
    data = RunData(
        params=[Param(k, v) for k, v in params.items()],
        tags=[RunTag("algo", algo), RunTag("seed", params.get("seed", "0"))],
    )
    return Run(info, data)


def td3(run_id: str, **changes: str) -> Run:
    return mlflow_run(run_id, **{**TD3, **changes})


# --- which keys make an arm -------------------------------------------------------------------


@pytest.mark.parametrize(
    "key",
    ["seed", "tracking.uri", "tracking.run_name", "sweep.trial_number", "sweep.pruner",
     "work_dir", "torch_threads", "population", "algo.compile", "dataset_stats.steps",
     "optimized_metric", "log_every", "resume", "env.published", "job_key"],
)  # fmt: skip
def test_keys_that_cannot_change_results_are_not_the_experiment(key):
    assert arms.is_not_the_experiment(key)


@pytest.mark.parametrize(
    "key", ["algo.lr", "algo.hidden_sizes", "env.id", "total_steps", "eval_episodes", "dataset",
            "trackingx", "seeds", "sweeps.x"],
)  # fmt: skip
def test_keys_that_shape_the_run_are_the_experiment(key):
    assert not arms.is_not_the_experiment(key)


def test_arm_config_drops_plumbing_and_cpu_devices_but_keeps_an_accelerator():
    params = {**TD3, "seed": "3", "tracking.uri": "sqlite:///x.db", "device": "auto"}
    assert arms.arm_config(params) == TD3
    assert arms.arm_config({**params, "device": "cpu"}) == TD3
    assert arms.arm_config({**params, "device": "cuda"}) == {**TD3, "device": "cuda"}
    without = arms.arm_config(params, exclude=["algo.hidden_sizes"])
    assert "algo.hidden_sizes" not in without and without["algo.lr"] == "0.0003"


def test_differing_keys_counts_a_missing_key_as_a_value():
    a, b, c = {"x": "1", "y": "2"}, {"x": "1", "y": "3"}, {"x": "1"}
    assert arms.differing_keys([a, a]) == []
    assert arms.differing_keys([a, b]) == ["y"]
    assert arms.differing_keys([a, c]) == ["y"]
    assert arms.differing_keys([]) == []


# --- names and order -------------------------------------------------------------------------


def test_natural_order_numbers_by_value_and_layer_lists_by_total_units():
    values = ["[256, 256]", "[64, 64]", "[256]", "[64, 64, 64]"]
    assert sorted(values, key=arms.natural_key) == ["[64, 64]", "[64, 64, 64]", "[256]",
                                                    "[256, 256]"]  # fmt: skip
    rates = ["0.001", "3e-05", "0.0003"]
    assert sorted(rates, key=arms.natural_key) == ["3e-05", "0.0003", "0.001"]
    assert sorted(["10", "9", "b", "a"], key=arms.natural_key) == ["9", "10", "a", "b"]


def test_arm_name():
    assert arms.arm_name("td3", {}) == "td3"
    assert arms.arm_name("td3", {"algo.hidden_sizes": "[64, 64]"}) == (
        "td3 (algo.hidden_sizes=[64, 64])"
    )
    # the algorithm first, its class path redundant beside it; where algorithms differ, their
    # own hyperparameters are implied by the name (spelled out where names would collide)
    distinct = {"algo._target_": "walkers.agents.td3.TD3", "algo.lr": "0.001", "algo.name": "td3"}
    assert arms.arm_name("g", distinct) == "g (algo.name=td3)"
    assert arms.arm_name("g", distinct, limit=3) == "g (algo.name=td3, algo.lr=0.001)"
    assert arms.arm_name("g", distinct | {"seed_list": "[1]"}) == "g (algo.name=td3, seed_list=[1])"
    many = {f"algo.k{i}": str(i) for i in range(5)}
    assert arms.arm_name("td3", many) == "td3 (algo.k0=0, algo.k1=1, algo.k2=2, +2 more)"


def test_parse_group_by():
    assert arms.parse_group_by(None) == []
    assert arms.parse_group_by("algo.lr") == ["algo.lr"]
    assert arms.parse_group_by("algo.lr, algo.tau") == ["algo.lr", "algo.tau"]
    assert arms.parse_group_by(OmegaConf.create({"g": ["algo.lr", "algo.tau"]}).g) == [
        "algo.lr",
        "algo.tau",
    ]


def test_a_bare_comma_list_on_the_command_line_is_a_list_not_a_sweep():
    args = ["env=pendulum", "group_by=algo.lr,algo.tau", "algos=[td3,ddpg]"]
    assert group_by_as_list(args) == ["env=pendulum", "group_by=[algo.lr,algo.tau]", args[2]]
    for kept in ("group_by=algo.lr", "group_by=[algo.lr,algo.tau]", "group_by='algo.lr,algo.tau'"):
        assert group_by_as_list([kept]) == [kept]


def test_unknown_key_hint_suggests_a_close_key_and_lists_the_varying_ones_first():
    params = [{**TD3, "seed": "0"}, {**TD3, "seed": "1", "algo.lr": "0.001"}]
    hint = arms.unknown_key_hint("algo.hiden_sizes", params)
    assert hint.startswith("did you mean 'algo.hidden_sizes'? keys the runs have: algo.lr, ")
    assert "seed" in hint  # listed, after the keys worth a study


# --- building arms from runs -----------------------------------------------------------------


def test_one_configuration_per_algorithm_keeps_plain_names_and_the_algos_order():
    runs = [
        td3("t0", seed="0"),
        td3("t1", seed="1", log_every="50", torch_threads="1"),  # plumbing only: same arm
        mlflow_run("r0", algo="reinforce", **{**TD3, "algo.name": "reinforce", "seed": "0"}),
    ]
    built, left_out, splits = arms.build_arms(runs, algos=["td3", "reinforce"])
    assert [(a.name, [r.info.run_id for r in a.runs]) for a in built] == [
        ("td3", ["t0", "t1"]),
        ("reinforce", ["r0"]),
    ]
    assert left_out == splits == []
    assert [a.name for a in arms.build_arms(runs)[0]] == ["reinforce", "td3"]  # by name


def test_configurations_of_one_algorithm_are_split_and_listed_never_pooled():
    runs = [
        td3("big0", **{"algo.hidden_sizes": "[256, 256]"}),
        td3("small0", **{"algo.hidden_sizes": "[64, 64]"}),
        td3("big1", **{"algo.hidden_sizes": "[256, 256]", "seed": "1"}),
    ]
    built, left_out, notes = arms.build_arms(runs)
    assert left_out == []
    assert [(a.name, [r.info.run_id for r in a.runs]) for a in built] == [
        ("td3 (algo.hidden_sizes=[64, 64])", ["small0"]),
        ("td3 (algo.hidden_sizes=[256, 256])", ["big0", "big1"]),
    ]
    assert built[0].distinct == {"algo.hidden_sizes": "[64, 64]"} and built[0].algo == "td3"
    (note,) = notes
    assert note.startswith("td3: 2 configurations") and "never pooled" in note
    assert "differ in algo.hidden_sizes" in note and "[256, 256]): 2 runs" in note


def test_a_seed_trained_twice_counts_once_and_the_report_says_which_run():
    """The same command run twice without a job key trains seed 0 twice: one sample, not two
    (two would narrow every interval); the latest run counts."""
    first, again = td3("first", seed="0"), td3("again", seed="0")
    first.info._start_time, again.info._start_time = 10, 20
    built, left_out, _ = arms.build_arms([again, first, td3("one", seed="1")])
    assert [[r.info.run_id for r in a.runs] for a in built] == [["again", "one"]]
    (note,) = left_out
    assert (
        note == "td3: seed 0 has 2 finished runs; the latest, again, counts (one sample per "
        "seed), not first"
    )


def test_shortened_names_that_collide_are_spelled_out():
    base = {f"algo.k{i}": "0" for i in range(4)}
    a = td3("a", **base)
    b = td3("b", **{**base, "algo.k3": "1"})
    built, _, _ = arms.build_arms([a, b])
    assert len({arm.name for arm in built}) == 2
    assert all("+1 more" not in arm.name and "algo.k3=" in arm.name for arm in built)


def test_group_by_makes_one_arm_per_value_in_natural_order():
    runs = [
        td3(f"{size}-{seed}", seed=str(seed), **{"algo.hidden_sizes": size})
        for size in ("[256, 256]", "[64, 64]")
        for seed in (0, 1)
    ]
    # a run of code that recorded neither the key nor its algorithm's class (so no declared
    # default stands in for it)
    unknown = ("algo.hidden_sizes", "algo._target_")
    runs.append(mlflow_run("old", **{k: v for k, v in TD3.items() if k not in unknown}))
    built, left_out, splits = arms.build_arms(runs, group_by=["algo.hidden_sizes"])
    assert [a.name for a in built] == [
        "algo.hidden_sizes=[64, 64]",
        "algo.hidden_sizes=[256, 256]",
    ]
    assert splits == []
    assert built[1].group_values == {"algo.hidden_sizes": "[256, 256]"}
    assert [len(a.runs) for a in built] == [2, 2]
    (note,) = left_out  # the run without the key is left out, and said so
    assert "without algo.hidden_sizes" in note and "old" in note
    assert set(arms.series(built).values()) == {""}  # one line in the plot


def test_group_by_still_splits_a_value_holding_several_configurations():
    runs = [
        td3("a", **{"algo.hidden_sizes": "[64, 64]"}),
        td3("b", **{"algo.hidden_sizes": "[64, 64]", "algo.lr": "0.001"}),
        td3("c", **{"algo.hidden_sizes": "[256, 256]", "algo.lr": "0.001"}),
    ]
    built, _, notes = arms.build_arms(runs, group_by=["algo.hidden_sizes"])
    assert [a.name for a in built] == [
        "algo.hidden_sizes=[64, 64] (algo.lr=0.0003)",
        "algo.hidden_sizes=[64, 64] (algo.lr=0.001)",
        "algo.hidden_sizes=[256, 256]",
    ]
    assert len(notes) == 1 and notes[0].startswith("algo.hidden_sizes=[64, 64]: 2 configurations")
    # the plot's lines: one per remaining configuration, across the values
    assert arms.series(built) == {
        built[0].name: "algo.lr=0.0003",
        built[1].name: "algo.lr=0.001",
        built[2].name: "algo.lr=0.001",
    }


# --- the report's side of it -----------------------------------------------------------------


def test_mlflow_keys_of_arm_names_are_valid():
    for name in ("td3", "td3 (algo.hidden_sizes=[64, 64])", "algo.lr=0.001 (algo.name=ddpg)"):
        key = mlflow_key(name)
        assert validate_param_and_metric_name(f"runs.{key}") and validate_param_and_metric_name(
            f"{key}/iqm"
        )
    assert mlflow_key("td3") == "td3"


def _seed_runs(algo: str, finals: list[float]) -> list[SeedRun]:
    steps = np.array([100, 200])
    summary = {"final/auc": 0.0, "final/steps_to_threshold": np.inf}
    return [
        SeedRun(f"{algo}{i}", algo, str(i), steps, np.array([0.0, f]),
                {**summary, "final/return_mean": f})
        for i, f in enumerate(finals)
    ]  # fmt: skip


def test_the_rate_of_learning_is_compared_only_between_arms_evaluated_alike():
    """The AUC is the mean of a run's evaluations: TD3 every 100 steps against DT every 200 over
    the same budget would favour the coarser grid on a rising curve; no AUC pair is formed. An
    AUC difference the second arm wins reliably is said of it, not called "no difference"."""
    slow = _seed_runs("slow", [100, 101, 102, 103, 104, 105])
    fast = _seed_runs("fast", [90, 91, 92, 93, 94, 95])
    for i, run in enumerate(fast):
        run.summary["final/auc"] = 80.0 + i  # reaches its level sooner
    for i, run in enumerate(slow):
        run.summary["final/auc"] = 40.0 + i
    settings = {"env_id": "Pendulum-v1", "threshold": -200.0, "budgets": {"env_steps": 200},
                "score": "final/return_mean", "n_resamples": 200}  # fmt: skip
    both = compare_groups({"slow": slow, "fast": fast}, ["slow", "fast"], **settings)
    assert [p.quantity for p in both.pairs] == ["score", "auc"]
    said = markdown(both, source="test")
    assert "fast learns faster (AUC (rate of learning): P(fast > slow) = 1 [1, 1]" in said, said
    assert "no reliable difference in AUC" not in said
    for run in fast:
        run.steps = np.array([200])
        run.returns = np.array([run.summary["final/return_mean"]])
    coarser = compare_groups({"slow": slow, "fast": fast}, ["slow", "fast"], **settings)
    assert [p.quantity for p in coarser.pairs] == ["score"]


def test_published_figures_stand_beside_the_measured_ones_for_the_algorithms_reported():
    env = compose_cfg(["env=walker2d"], config_name="compare").env
    figures = published_figures(env, ["td3"])
    assert figures and {f["algo"] for f in figures} == {"td3"}
    assert published_figures(env, ["dt"]) == []
    comparison = compare_groups(
        {"td3": _seed_runs("td3", [3000, 3100, 3200]), "dt": _seed_runs("dt", [10, 20, 30])},
        ["td3", "dt"],
        env_id=env.id,
        threshold=env.threshold,
        budgets={"env_steps": 1_000_000},
        score="final/return_mean",
        n_resamples=200,
    )
    comparison.published = figures
    report = markdown(comparison, source="test")
    section = report.split("## Published reference figures")[1].split("##")[0]
    assert PUBLISHED_CAVEAT in section and f"This report measured {env.id}" in section
    rows = [line for line in section.splitlines() if line.startswith("| td3 |")]
    assert len(rows) == len(figures)
    for row, figure in zip(rows, figures, strict=True):
        assert f"| {figure['return']:,}" in row and "(published)" in row  # as published
        assert f"{figure['env_version']} (other version)" in row
        assert "td3 3,100" in row  # the measured IQM beside it
    assert "| dt |" not in section


def test_a_run_from_before_a_key_existed_joins_the_arm_of_that_keys_old_value(store):
    """Runs logged before ``impl`` existed were trained by walkers: they are seeds of the
    impl=walkers arm, not an arm "(not set)" of their own, and a study by impl finds them."""
    client = store["client"]
    experiment = get_or_create_experiment(client, "later_keys")

    def logged(seed: int, **params: str):
        run = client.create_run(experiment, tags={"algo": "td3"})
        for key, value in {"algo.name": "td3", "seed": str(seed), **params}.items():
            client.log_param(run.info.run_id, key, value)
        return client.get_run(run.info.run_id)

    old, new, twin = logged(0), logged(1, impl="walkers"), logged(0, impl="sb3")
    found, left_out, _ = arms.build_arms([old, new, twin], group_by=["impl"])
    assert left_out == []
    by_name = {a.name: {r.info.run_id for r in a.runs} for a in found}
    assert by_name == {
        "impl=sb3": {twin.info.run_id},
        "impl=walkers": {old.info.run_id, new.info.run_id},
    }
    (single,) = arms.build_arms([old, new])[0]
    assert len(single.runs) == 2  # one arm, two seeds


def test_a_run_from_before_a_hyperparameter_was_declared_joins_the_arm_of_its_default(store):
    """TD3's 100k Walker2d baseline: seeds 0-2 trained before algo.capture was declared, seeds
    3-5 after, with its default (auto: eager on a CPU). One arm of six seeds, not "td3
    (algo.capture=(not set))" beside "td3 (algo.capture=auto)"; a run that set another value
    stays apart."""
    client = store["client"]
    experiment = get_or_create_experiment(client, "declared_later")
    base = {"algo._target_": "walkers.agents.td3.TD3", "algo.name": "td3", "algo.lr": "0.001"}

    def logged(seed: int, **params: str):
        run = client.create_run(experiment, tags={"algo": "td3"})
        for key, value in {**base, "seed": str(seed), **params}.items():
            client.log_param(run.info.run_id, key, value)
        return client.get_run(run.info.run_id)

    before = [logged(seed) for seed in range(3)]
    after = [logged(seed, **{"algo.capture": "auto"}) for seed in range(3, 6)]
    other = logged(6, **{"algo.capture": "true"})
    assert arms.run_params(before[0])["algo.capture"] == "auto"  # its declared default
    found, _, splits = arms.build_arms([*before, *after, other])
    assert {a.name: len(a.runs) for a in found} == {
        "td3 (algo.capture=auto)": 6,
        "td3 (algo.capture=true)": 1,
    }
    assert len(splits) == 1


def test_rendering_a_report_imports_no_mlflow_and_a_comparison_no_torch():
    """The report only renders a comparison: its data model and the names of axes come from
    modules that import no MLflow (walkers.tracking.names), and a run's tracker brings it. Comparing
    runs, and refusing a typo on any command line, import no torch (seconds of a user's wait),
    nor does the digest of the code that trains a run: only a reference arm's fingerprint
    needs it."""
    code = (
        "import sys, walkers.analysis.report, walkers.tracking.names; "
        "assert 'mlflow' not in sys.modules, 'mlflow imported'; "
        "from walkers.tracking.client import Tracker; "
        "assert 'mlflow' in sys.modules; "
        "import walkers.compare, walkers.cli, walkers.training.provenance as p; "
        "assert len(p.code_digest()) == 16; "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
