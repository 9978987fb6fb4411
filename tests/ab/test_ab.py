"""A/B studies (``-m ab=NAME``), run as a user runs them: real jobs, real stores, a real kill -9
of the driver, and the rerun that picks up where it stopped."""

from __future__ import annotations

import collections
import itertools
import os
import re

import pytest
from omegaconf import OmegaConf

from tests.conftest import all_runs, compose_cfg, one_line_error, run_cli
from tests.study_kit import (
    OBVIOUS,
    OBVIOUS_TD3,
    arms,
    job_runs,
    refusal_in_process,
    study,
    study_run,
)
from walkers import CONF_DIR
from walkers.ab import ledger
from walkers.ab.spec import StudySpec
from walkers.errors import ConfigError
from walkers.plan import make_plan
from walkers.tracking.bundles import read_bundle
from walkers.training.settings import validate


def test_an_obvious_difference_stops_at_the_minimum_seeds_and_a_rerun_runs_nothing(store):
    result = run_cli(study(store, *OBVIOUS), cwd=store["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    runs = job_runs(store)
    assert len(runs) == 10 and {r.info.status for r in runs} == {"FINISHED"}
    seeds = collections.Counter(r.data.tags["walkers.job_key"].rsplit("/", 1)[0] for r in runs)
    assert seeds == {"ab/t/short/pendulum": 5, "ab/t/long/pendulum": 5}
    parent = study_run(store)
    assert parent.info.status == "FINISHED"
    assert {r.data.tags["mlflow.parentRunId"] for r in runs} == {parent.info.run_id}
    assert parent.data.tags["answer.short_vs_long_on_pendulum"] == "A better"
    assert "short is better than long on pendulum (5 seeds per arm" in result.stdout
    assert "?workflowType=machine_learning" in result.stdout  # the link opens the runs view
    # before its first round a study says what the round will cost: from the committed results'
    # runs of its algorithms where its arms have none of their own yet
    said = result.stdout + result.stderr
    cost = re.search(
        r"study 't', look 1: (about ([0-9.e-]+) CPU-hours|its CPU-hours are not)", said
    )
    assert cost, said[-3000:]
    # by default a round's jobs run side by side, one a core, one torch thread each
    assert {r.data.params["torch_threads"] for r in runs} == {"1"}
    assert len({r.data.tags["walkers.multirun_job"] for r in runs}) == 10
    spans = sorted((r.info.start_time, r.info.end_time) for r in runs)
    overlapping = any(later[0] < earlier[1] for earlier, later in itertools.pairwise(spans))
    assert overlapping == ((os.cpu_count() or 1) > 1), spans
    for arm in ("short", "long"):  # what each arm cost: the sum of its runs' own counts
        spent = sum(
            r.data.metrics["final/cpu_hours"]
            for r in runs
            if f"/{arm}/" in r.data.tags["walkers.job_key"]
        )
        assert parent.data.metrics[f"ab/cpu_hours.{arm}"] == pytest.approx(spent) and spent > 0
    spent_line = r"CPU-hours of the finished runs: (short|long) [0-9.e-]+, (long|short) [0-9.e-]+\n"
    assert re.search(spent_line, result.stdout)
    # what an env step of each arm costs, for a next round's estimate: its runs' own mean
    declared = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "ab" / "tiny.yaml").hydra.sweeper)
    spec = StudySpec.parse(
        **declared | {"name": "t", "arms": {"short": "", "long": ""}, "envs": ["pendulum"]}
    )
    rates = ledger.hours_per_step(runs, spec)
    for arm in ("short", "long"):
        per_step = [
            r.data.metrics["final/cpu_hours"] / 400
            for r in runs
            if f"/{arm}/" in r.data.tags["walkers.job_key"]
        ]
        assert rates[(arm, "pendulum")] == pytest.approx(sum(per_step) / len(per_step))
    # it ends with its report and its bundle, and says where they are
    assert "report: reports/ab_tiny/Pendulum-v1/report.md" in result.stdout
    assert "bundle: reports/ab_tiny/bundle (11 runs" in result.stdout
    report = (store["path"] / "reports/ab_tiny/Pendulum-v1/report.md").read_text()
    assert "reinforce (env.max_episode_steps=100)" in report
    bundle = read_bundle(store["path"] / "reports/ab_tiny/bundle")
    assert {r["origin"] for r in bundle["runs"]} == {r.info.run_id for r in runs} | {
        parent.info.run_id
    }

    again = run_cli(study(store, *OBVIOUS), cwd=store["path"])
    assert again.returncode == 0, again.stderr[-3000:]
    assert len(job_runs(store)) == 10  # nothing ran twice
    assert "bundle: reports/ab_tiny/bundle (11 runs" in again.stdout  # written again, whole
    assert "short is better than long on pendulum (5 seeds per arm" in again.stdout
    assert study_run(store).info.status == "FINISHED"

    # the study file edited: an arm is one configuration, so a changed arm is refused
    edited = arms(
        "{short:'algo=reinforce env.max_episode_steps=100',long:'algo=reinforce algo.lr=0.01'}"
    )
    line = one_line_error(run_cli(study(store, *edited), cwd=store["path"]))
    assert "arm 'long' on pendulum has changed since its runs started (algo.lr" in line
    assert len(job_runs(store)) == 10


@pytest.mark.slow  # `make test-slow`: a study of two rounds
def test_a_rounds_new_seeds_train_as_one_population_each_its_own_job(store):
    """seeds_as_population (the default on a GPU, forced here on the CPU): each arm's five fresh
    seeds are one population job, and each member is the run its seed's job would be."""
    args = study(store, *OBVIOUS_TD3, "hydra.sweeper.seeds_as_population=true")
    result = run_cli(args, cwd=store["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    said = result.stdout + result.stderr
    assert "launching 2 jobs (10 seeds)" in said
    assert "each round's new seeds run as one population job for long on pendulum" in said
    runs = job_runs(store)
    keys = sorted(r.data.tags["walkers.job_key"] for r in runs)
    assert keys == sorted(f"ab/t/{arm}/pendulum/{s}" for arm in ("long", "short") for s in range(5))
    for run in runs:
        key, seed = run.data.tags["walkers.job_key"], run.data.params["seed"]
        assert run.info.status == "FINISHED" and key.endswith(f"/{seed}")
        assert run.data.tags["walkers.population"] == "5" and run.data.params["population"] == "1"
        assert run.data.tags["mlflow.runName"] == f"ab-t-{key.split('/')[2]}-pendulum-s{seed}"
    assert "short is better than long on pendulum (5 seeds per arm" in result.stdout

    again = run_cli(args, cwd=store["path"])
    assert again.returncode == 0, again.stderr[-3000:]
    assert len(job_runs(store)) == 10 and "launching" not in again.stdout + again.stderr


def test_seeds_as_population_is_checked_in_one_line(store, capsys):
    line = refusal_in_process(store, capsys, "hydra.sweeper.seeds_as_population=yes")
    assert (
        "hydra.sweeper.seeds_as_population='yes' is not allowed: one of auto, true, false" in line
    )
    line = refusal_in_process(store, capsys, "population=3")
    assert "population=3: the study sets population for each job" in line
    assert job_runs(store) == []


@pytest.mark.slow  # `make test-slow`: a whole study (the rule's error rates are simulated in
# tests/analysis/test_sequential.py in the default suite)
def test_two_identical_arms_end_equal_or_not_settled_never_better(store):
    same = arms("{a:'algo=reinforce',b:'algo=reinforce'}")
    result = run_cli(study(store, *same, "hydra.sweeper.smallest_difference=50"), cwd=store["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    answer = study_run(store).data.tags["answer.a_vs_b_on_pendulum"]
    assert answer in ("equal", "not settled")
    per_arm = collections.Counter(
        r.data.tags["walkers.job_key"].split("/")[2] for r in job_runs(store)
    )
    assert per_arm["a"] == per_arm["b"] <= 7


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        (arms("{a:'algo=a2c',b:'algo=td3'}"), "arm 'a': algo='a2c' is not allowed: must be one of"),
        ("hydra.sweeper.alpha=1.5", "hydra.sweeper.alpha=1.5 is not allowed: must be a number"),
        (arms("{a:'algo=td3 algo.lr=-1',b:'algo=td3'}"), "arm 'a' on pendulum: algo.lr=-1"),
        ("seed=0,1", "seed=0,1: a study runs its own seeds and arms"),
    ],
)
def test_bad_studies_are_refused_in_one_line_before_anything_runs(
    store, capsys, override, expected
):
    overrides = override if isinstance(override, list) else [override]
    line = refusal_in_process(store, capsys, *overrides)
    assert expected in line, line
    assert all_runs(store["client"]) == []


@pytest.mark.parametrize(
    ("changed", "expected"),
    [
        ({"envs": ["pendulum", "walker3d"]}, "env='walker3d' is not allowed: must be one of"),
        ({"seeds": {"min": 5, "max": 3, "per_round": 1}}, "seeds.max=3 is not allowed: at least"),
        ({"alpha": 0.0}, "hydra.sweeper.alpha=0.0 is not allowed: must be a number in (0, 1)"),
        ({"arms": {"only": "algo=td3"}}, "a mapping of at least two arms"),
        (
            {"arms": {"a": "algo=td3 seed=3", "b": "algo=td3"}},
            "the study sets seed, env and job_key",
        ),
        ({"score": "final/steps_to_threshold"}, "hydra.sweeper.score='final/steps_to_threshold'"),
    ],
)
def test_the_study_declaration_is_checked_in_one_line(changed, expected):
    """The same checks the sweeper runs first (in-process: one CLI case above proves the line)."""
    declared = {
        "name": "t",
        "arms": {"a": "algo=td3", "b": "algo=sac"},
        "envs": ["pendulum"],
        "seeds": {"min": 5, "max": 7, "per_round": 1},
        "score": "final/return_mean",
        "alpha": 0.05,
        "smallest_difference": 10,
    }
    with pytest.raises(ConfigError) as refused:
        StudySpec.parse(**(declared | changed))
    assert expected in str(refused.value)
    assert "\n" not in str(refused.value)


def test_a_study_without_multirun_is_refused(store):
    line = one_line_error(run_cli(["ab=tiny", *store["overrides"]], cwd=store["path"]))
    assert "ab=tiny is an A/B study: run it with -m" in line


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF_DIR / "ab").glob("*.yaml")))
def test_every_shipped_study_is_sound(name):
    """Each study in conf/ab/ parses, passes the sweeper's check that a look can decide, can
    decide at its first look, and every arm composes and
    validates on every env (what its sweeper checks before anything runs)."""
    declared = OmegaConf.to_container(
        OmegaConf.load(CONF_DIR / "ab" / f"{name}.yaml").hydra.sweeper
    )
    spec = StudySpec.parse(**declared)
    assert spec.checked_design().first_look_can_decide()
    for arm in spec.arms:
        for env in spec.envs:
            validate(compose_cfg([*arm.overrides, f"env={env}"]))


#: The design a user wrote (issue 53): 3 questions, at most 4 seeds per arm; no look can decide.
NEVER_DECIDES = [
    *arms("{td3:'algo=td3',ddpg:'algo=ddpg algo.critic_layer_norm=true'}"),
    "hydra.sweeper.envs=[bipedal_walker,hopper]",
    "hydra.sweeper.seeds={min:3,max:4,per_round:1}",
    "hydra.sweeper.name=mine",
]


def test_a_study_that_can_never_decide_is_refused_with_nothing_created(store):
    result = run_cli(["-m", "ab=tiny", *NEVER_DECIDES, *store["overrides"]], cwd=store["path"])
    line = one_line_error(result)
    assert line == (
        "error: study 'mine': with 3 questions and at most 4 seeds per arm no look can reach its "
        "level (the fewest that can: 7); raise hydra.sweeper.seeds.max"
    )
    assert all_runs(store["client"]) == []
    assert [e.name for e in store["client"].search_experiments()] == ["Default"]
    assert not (store["path"] / "work").exists() and not (store["path"] / "multirun").exists()
    # walkers.plan shows the same design look by look, and the sweeper's verdict on it
    with pytest.raises(Exception, match="hydra"):  # plan names a study by file or conf/ab name,
        compose_cfg(["study=ab/tiny", *NEVER_DECIDES], config_name="plan")  # not by overrides
    study_file = store["path"] / "mine.yaml"
    study_file.write_text(
        "hydra:\n  sweeper:\n    name: mine\n    arms: {td3: algo=td3, ddpg: algo=ddpg}\n"
        "    envs: [bipedal_walker, hopper]\n    seeds: {min: 3, max: 4, per_round: 1}\n"
        "    score: final/return_mean\n    alpha: 0.05\n    smallest_difference: 10\n"
    )
    plan = make_plan(compose_cfg([f"study={study_file}"], config_name="plan"))
    assert "| 1 | 3 | 0.0138 | 0.1 | no | no | 5 |" in plan
    assert "| 2 | 4 | 0.00287 | 0.0286 | no | no | 6 |" in plan
    assert "refused by the sweeper: study 'mine': with 3 questions" in plan
    assert "'equal' can never be answered" in plan


@pytest.mark.slow  # 10 jobs through two looks
def test_a_study_whose_first_look_cannot_decide_runs_with_a_warning(store):
    """3 seeds per arm can never reach alpha 0.05 (smallest p 0.1), 5 can: the study runs its
    looks, says so in one line, and records the looks that can decide on its run."""
    late = "hydra.sweeper.seeds={min:3,max:5,per_round:2}"
    result = run_cli(study(store, *OBVIOUS, late), cwd=store["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert warnings == [
        "warning: study 't': at 3 seeds per arm no look can decide anything whatever the returns "
        "(only 'continue'); the looks at 5 can (`python -m walkers.plan study=...` shows each look)"
    ]
    parent = study_run(store)
    assert parent.data.tags["ab.deciding_looks"] == "5"
    assert parent.data.tags["ab.equal_looks"] == "5"
    assert parent.data.tags["answer.short_vs_long_on_pendulum"] == "A better"
    assert len(job_runs(store)) == 10  # the look at 3 continued, the look at 5 decided


def test_a_study_rerun_with_another_design_is_refused_and_its_normalization_is_part_of_it(
    store, monkeypatch
):
    """A study's test is fixed when it starts: its alpha, or an env's normalization re-measured
    since (a random score from benchmarks/random_scores.py), would move what its looks answered;
    a study from before the normalization was recorded is not held to it."""
    import dataclasses

    from walkers.ab import ledger
    from walkers.ab.spec import EnvScores

    declared = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "ab" / "tiny.yaml").hydra.sweeper)
    spec = StudySpec.parse(**declared)
    client = store["client"]
    ledger.open_study_run(client, "designs", spec, store["path"]).end("KILLED")
    (study,) = all_runs(client)
    assert "pendulum: random=" in study.data.params["ab.normalization"]

    moved = dict(spec.scores, pendulum=EnvScores(-1500.0, spec.scores["pendulum"].reference))
    for changed, key in [
        (dataclasses.replace(spec, alpha=0.01), "ab.alpha"),
        (dataclasses.replace(spec, scores=moved), "ab.normalization"),
    ]:
        with pytest.raises(ConfigError) as refused:
            ledger.open_study_run(client, "designs", changed, store["path"])
        assert str(refused.value).startswith(
            f"study 'tiny' in experiment 'designs' was started with {key}="
        )
        assert "a study's test is fixed when it starts" in str(refused.value)
    assert client.get_run(study.info.run_id).info.status == "KILLED"  # not reopened
    ledger.open_study_run(client, "designs", spec, store["path"]).end("FINISHED")  # the same: on

    older = client.create_run(  # a study started before its normalization was recorded
        client.get_experiment_by_name("designs").experiment_id,
        tags={"walkers.kind": "ab", "walkers.ab": "older"},
    )
    for key, value in spec.design_params().items():
        if key != "ab.normalization":
            client.log_param(older.info.run_id, key, value)
    client.set_terminated(older.info.run_id, "KILLED")
    renamed = dataclasses.replace(spec, name="older", scores=moved)
    assert ledger.open_study_run(client, "designs", renamed, store["path"]).run_id == (
        older.info.run_id
    )


def test_a_rounds_cost_puts_each_launch_on_the_job_slot_that_frees_first():
    """Hand-worked: what a study says a round will cost, from rates of 1 and 2 CPU-hours a step
    and launches of 3, 1, 1 and 1 steps."""
    launches = [("a", "e", [0]), ("b", "e", [0]), ("b", "e", [1]), ("b", "e", [2])]
    rates, left = {("a", "e"): 1.0, ("b", "e"): 2.0}, [3, 1, 1, 1]
    assert ledger.expected_cost(launches, left, rates, parallel=2) == (  # 3 + 2 + 2 + 2 = 9;
        "about 9 CPU-hours at the CPU time its arms' runs measured; about 5 h of wall time, "
        "2 jobs at a time"  # the slots: a's 3 h, then b's third 2 h | b's first two, 2 + 2 h
    )
    on_one = ledger.expected_cost(launches, left, rates, parallel=1, from_results={("a", "e")})
    assert on_one.endswith(
        "(a on e: the committed results' runs of its algorithm); about 9 h of wall time, one job "
        "at a time"
    )
    assert ledger.expected_cost(launches, left, rates, parallel=None).endswith("measured")
    unknown = ledger.expected_cost(launches, left, {("a", "e"): 1.0}, parallel=2)
    assert unknown.startswith("its CPU-hours are not known yet: no run of b on e has measured")
