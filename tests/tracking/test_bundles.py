"""Results bundles (``walkers.export``, ``walkers.ingest``) on real stores: a real tiny study
exported, imported into fresh stores, reported on, rerun, and real bad bundles refused."""

from __future__ import annotations

import gzip
import json
import shutil

import pytest
from mlflow.tracking import MlflowClient

from tests.conftest import all_runs, compose_cfg, new_store, one_line_error, run_cli
from tests.study_kit import OBVIOUS, arms, export, ingest, study
from walkers.analysis.comparison import compare
from walkers.errors import ConfigError
from walkers.export import export as export_runs
from walkers.tracking import bundles
from walkers.tracking.client import get_or_create_experiment
from walkers.tracking.names import LOGGED_THROUGH_TAG


def report(store, *args: str) -> str:
    """The report of the study's runs (``walkers.compare`` in-process: its command line is
    tests/analysis/test_compare.py's), with each run id replaced by the run's origin."""
    out = store["path"] / "report"
    compare(
        compose_cfg(
            ["env=pendulum", "tracking.experiment=ab_tiny", f"out={out}", "log_report=false",
             *store["overrides"], *args],
            config_name="compare",
        )
    )  # fmt: skip
    text = (out / "report.md").read_text() + (out / "summary.json").read_text()
    text = text.replace(str(store["path"]), "<store>")
    for run in all_runs(store["client"]):
        text = text.replace(run.info.run_id, run.data.tags.get(bundles.ORIGIN_TAG, run.info.run_id))
    return text


def exported(store, *args: str) -> bundles.Exported:
    """``walkers.export`` in-process (the fixture runs its command line)."""
    overrides = ["tracking.experiment=ab_tiny", *args, f"tracking.uri={store['uri']}"]
    return export_runs(compose_cfg(overrides, config_name="export"))


#: How the reports compared here name their runs' source (the store's path would differ).
SOURCE = "source=the tiny study"


def compared_where_it_lies(bundle, cwd) -> str:
    """``walkers.compare bundle=BUNDLE`` in-process, run from ``cwd``: its report's text."""
    cwd.mkdir()
    cfg = compose_cfg(
        ["env=pendulum", f"bundle={bundle}", f"out={cwd / 'report'}", "log_report=false", SOURCE,
         f"tracking.uri=sqlite:///{cwd / 'never.db'}", f"work_dir={cwd / 'work'}"],
        config_name="compare",
    )  # fmt: skip
    compare(cfg)
    return (cwd / "report" / "report.md").read_text() + (
        cwd / "report" / "summary.json"
    ).read_text()


def test_a_bundle_compared_where_it_lies_names_what_is_wrong_in_one_line(studied, tmp_path):
    _, bundle, _ = studied
    wrong = compose_cfg([f"bundle={bundle}", "env=hopper", "log_report=false"],
                        config_name="compare")  # fmt: skip
    with pytest.raises(ConfigError) as refused:
        compare(wrong)
    assert f"no finished Hopper-v5 runs for any in bundle '{bundle}'" in str(refused.value)
    assert "algorithms with runs there: " in str(refused.value)
    with pytest.raises(ConfigError, match="is not a bundle"):
        compare(compose_cfg([f"bundle={tmp_path / 'nope'}"], config_name="compare"))


@pytest.fixture(scope="module")
def studied(tmp_path_factory):
    """A finished tiny study (2 arms x 5 seeds of 400 steps) in a store of its own, exported."""
    source = new_store(tmp_path_factory.mktemp("source"))
    result = run_cli(study(source, *OBVIOUS), cwd=source["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    done = export(source, "study=t", f"out={source['path'] / 'bundle'}")
    assert done.returncode == 0, done.stderr[-2000:]
    return source, source["path"] / "bundle", done.stdout


def test_an_imported_study_reports_to_the_digit_and_a_second_import_adds_nothing(studied, tmp_path):
    source, bundle, printed = studied
    assert f"exported 11 runs to {bundle}" in printed
    assert "Downloading artifacts" not in printed
    target = new_store(tmp_path)

    first = ingest(target, bundle)
    assert first.returncode == 0, first.stderr[-2000:]
    assert "imported 11 runs" in first.stdout and "(0 already there)" in first.stdout
    copies = {r.data.tags[bundles.ORIGIN_TAG]: r for r in all_runs(target["client"])}
    originals = {  # the study's run and its jobs' (not the report the study logged)
        r.info.run_id: r
        for r in all_runs(source["client"])
        if r.data.tags.get("walkers.kind") != "report"
    }
    assert copies.keys() == originals.keys()
    for origin, copy in copies.items():
        original = originals[origin]
        assert copy.info.status == original.info.status
        assert copy.info.start_time == original.info.start_time
        assert copy.data.params == original.data.params
        assert copy.data.metrics == original.data.metrics
        for key in ("eval/return_mean", "train/episode_return"):
            if key in original.data.metrics:  # every point: step, value and time
                history = [
                    [(m.step, m.value, m.timestamp) for m in c.get_metric_history(r, key)]
                    for c, r in ((source["client"], origin), (target["client"], copy.info.run_id))
                ]
                assert sorted(history[0]) == sorted(history[1])
        parent = original.data.tags.get("mlflow.parentRunId")
        if parent:  # nested under the imported study run, not the source store's id
            assert copies[parent].info.run_id == copy.data.tags["mlflow.parentRunId"]
        if copy.data.tags.get("walkers.kind") != "ab":  # a training run's composed config
            names = [f.path for f in target["client"].list_artifacts(copy.info.run_id)]
            assert "config.yaml" in names
    in_its_store = report(source, SOURCE)
    assert report(target, SOURCE) == in_its_store
    # and read where it lies (``walkers.compare bundle=``, what results/ pages are made by): the
    # same report, and nothing written but it
    assert compared_where_it_lies(bundle, tmp_path / "in_place") == in_its_store
    assert [p.name for p in (tmp_path / "in_place").iterdir()] == ["report"]

    second = bundles.import_bundle(target["client"], bundle)
    assert second.added == [] and second.present == 11
    assert len(all_runs(target["client"])) == 11

    # the study command on the new store finds it done: nothing runs
    again = run_cli(study(target, *OBVIOUS), cwd=target["path"])
    assert again.returncode == 0, again.stderr[-2000:]
    assert "short is better than long on pendulum (5 seeds per arm" in again.stdout
    trained = [r for r in all_runs(target["client"]) if r.data.tags.get("walkers.kind") != "report"]
    assert len(trained) == 11

    # and a bundle of the new store's copies goes home as nothing new: origins travel
    back = target["path"] / "back"
    assert exported(target, "study=t", f"out={back}").runs == 11
    assert bundles.import_bundle(source["client"], back).added == []


@pytest.mark.slow  # `make test-slow`: the study command again (the default suite: 10 minutes)
def test_a_study_that_trains_nothing_bundles_the_runs_it_decided_on(studied, tmp_path):
    """Its jobs' runs were in the store before its own run began (imported, the imported study
    run then deleted in the UI): it trains nothing, and the bundle it writes holds its run and
    the ten runs it decided on, not its run alone (the CrossQ study's rebuild, stop 62)."""
    _, bundle, _ = studied
    target = new_store(tmp_path)
    bundles.import_bundle(target["client"], bundle)
    (earlier,) = [r for r in all_runs(target["client"]) if r.data.tags.get("walkers.kind") == "ab"]
    target["client"].delete_run(earlier.info.run_id)

    again = run_cli(study(target, *OBVIOUS), cwd=target["path"])
    assert again.returncode == 0, again.stderr[-2000:]
    assert "short is better than long on pendulum (5 seeds per arm" in again.stdout
    own = [r for r in all_runs(target["client"]) if r.data.tags.get("walkers.kind") == "ab"]
    assert len(own) == 1 and own[0].info.run_id != earlier.info.run_id
    written = bundles.read_bundle(target["path"] / "reports/ab_tiny/bundle")["runs"]
    keys = sorted(r["tags"].get("walkers.job_key", "the study") for r in written)
    jobs = [f"ab/t/{arm}/pendulum/{seed}" for arm in ("long", "short") for seed in range(5)]
    assert keys == sorted(["the study", *jobs])


@pytest.mark.slow  # `make test-slow`: the study command on a copy of the study
def test_a_study_with_a_diverged_seed_stops_in_one_line_and_trains_nothing(studied, tmp_path):
    """A seed whose run diverged (FAILED, tagged with the step) is neither counted nor trained
    again by the same study command: one line names the job and the step, the study ends FAILED
    and no run is added (the study's own run, reopened, ends FAILED)."""
    from walkers.training.provenance import DIVERGED_TAG

    _, bundle, _ = studied
    target = new_store(tmp_path)
    bundles.import_bundle(target["client"], bundle)
    client = target["client"]
    (job,) = [
        r for r in all_runs(client) if r.data.tags.get("walkers.job_key") == "ab/t/long/pendulum/2"
    ]
    client.set_terminated(job.info.run_id, "FAILED")
    client.set_tag(job.info.run_id, DIVERGED_TAG, "300")
    before = {r.info.run_id for r in all_runs(client)}

    line = one_line_error(run_cli(study(target, *OBVIOUS), cwd=target["path"]), code=1)
    assert line == (
        f"error: job ab/t/long/pendulum/2 diverged at step 300 (run {job.info.run_id}): a study "
        "can neither count the seed nor train it again (a new attempt would diverge again, or "
        "leave the arm's failures out of its samples); change the arm (a lower learning rate, "
        "say) and run it as a new study"
    )
    after = all_runs(client)
    assert {r.info.run_id for r in after} == before  # the study's own run reopened, no job run
    assert [r.info.status for r in after if r.data.tags.get("walkers.kind") == "ab"] == ["FAILED"]


def _rewritten(bundle, tmp_path, change) -> str:
    copy = tmp_path / "edited"
    shutil.copytree(bundle, copy)
    with gzip.open(copy / bundles.RUNS_FILE, "rt") as f:
        document = json.load(f)
    change(document)
    with gzip.open(copy / bundles.RUNS_FILE, "wt") as f:
        json.dump(document, f)
    return str(copy)


def _truncated(bundle, tmp_path) -> str:
    copy = tmp_path / "truncated"
    shutil.copytree(bundle, copy)
    data = (copy / bundles.RUNS_FILE).read_bytes()
    (copy / bundles.RUNS_FILE).write_bytes(data[: len(data) // 2])
    return str(copy)


def test_a_truncated_bundle_is_refused_in_one_line_and_nothing_is_imported(studied, tmp_path):
    _, bundle, _ = studied
    target = new_store(tmp_path)
    line = one_line_error(ingest(target, _truncated(bundle, tmp_path)))
    assert "is truncated or corrupt" in line, line
    assert all_runs(target["client"]) == []
    assert [e.name for e in target["client"].search_experiments()] == ["Default"]


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (
            lambda b, t: _rewritten(b, t, lambda d: d.update(version=2)),
            "is version 2: this walkers reads version 1",
        ),
        (
            lambda b, t: _rewritten(b, t, lambda d: d["runs"].pop()),
            "is incomplete: its run count does not match",
        ),
        (
            lambda b, t: _rewritten(b, t, lambda d: d.update(format="mlflow-export-import")),
            "is not a walkers bundle (format 'walkers-bundle')",
        ),
        (lambda b, t: str(t / "nowhere"), "is not a bundle: it has no runs.json.gz"),
    ],
)
def test_a_foreign_or_damaged_bundle_is_refused_and_nothing_is_imported(
    studied, tmp_path, make, expected
):
    """The checks ``walkers.ingest`` runs first (in-process: the CLI case above proves the line)."""
    _, bundle, _ = studied
    target = new_store(tmp_path)
    with pytest.raises(ConfigError) as refused:
        bundles.import_bundle(target["client"], make(bundle, tmp_path))
    assert expected in str(refused.value)
    assert all_runs(target["client"]) == []
    assert [e.name for e in target["client"].search_experiments()] == ["Default"]


def test_a_run_that_conflicts_with_a_finished_one_is_refused_before_anything_is_written(
    studied, tmp_path
):
    """Another run of the same job already FINISHED in the target (the study ran there too):
    importing would count a seed twice."""
    _, bundle, _ = studied
    target = new_store(tmp_path)
    client = MlflowClient(target["uri"])
    experiment_id = get_or_create_experiment(client, "ab_tiny")
    theirs = client.create_run(experiment_id, tags={"walkers.job_key": "ab/t/short/pendulum/3"})
    client.set_terminated(theirs.info.run_id, "FINISHED")
    with pytest.raises(ConfigError) as refused:  # in-process: the truncated bundle's CLI case
        bundles.import_bundle(client, bundle)  # above proves the one line
    assert f"conflicts with run {theirs.info.run_id} already FINISHED" in str(refused.value)
    assert "(ab/t/short/pendulum/3)" in str(refused.value)
    assert [r.info.run_id for r in all_runs(client)] == [theirs.info.run_id]
    # into another experiment it goes whole
    assert len(bundles.import_bundle(client, bundle, "ab_tiny_copy").added) == 11


def _stopped_earlier(bundle, tmp_path):
    """The bundle as an export made while one job was still training would have been: that run
    KILLED, logged through an earlier step; returns (the bundle, that run's origin)."""
    stopped = {}

    def stop_one(document):
        record = next(r for r in document["runs"] if r["tags"].get("walkers.job_key"))
        record["status"] = "KILLED"
        record["tags"][LOGGED_THROUGH_TAG] = "200"
        stopped["origin"] = record["origin"]

    return _rewritten(bundle, tmp_path, stop_one), stopped["origin"]


def _copy_of(store, origin: str):
    (copy,) = [r for r in all_runs(store["client"]) if r.data.tags[bundles.ORIGIN_TAG] == origin]
    return copy


def test_a_later_bundle_replaces_copies_that_went_on_since_and_refuses_two_continuations(
    studied, tmp_path
):
    """A study exported from a GPU box mid-way, imported, then exported again once done: the
    second import brings the run that was KILLED as FINISHED (a study command here then has
    nothing to run), a third adds nothing. A copy trained on here as well is a conflict."""
    _, bundle, _ = studied
    earlier, origin = _stopped_earlier(bundle, tmp_path)
    target = new_store(tmp_path / "home")
    assert len(bundles.import_bundle(target["client"], earlier).added) == 11
    assert _copy_of(target, origin).info.status == "KILLED"

    done = ingest(target, bundle)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "imported 1 runs from " in done.stdout
    assert ", 1 of them later versions of earlier copies (10 already there)" in done.stdout
    runs = all_runs(target["client"])
    assert len(runs) == 11 and {r.info.status for r in runs} == {"FINISHED"}
    now = _copy_of(target, origin)
    study = next(r for r in runs if r.data.tags.get("walkers.kind") == "ab")
    assert now.data.tags["mlflow.parentRunId"] == study.info.run_id
    third = bundles.import_bundle(target["client"], bundle)
    assert third.added == [] and third.present == 11

    elsewhere = new_store(tmp_path / "elsewhere")
    bundles.import_bundle(elsewhere["client"], earlier)
    copy = _copy_of(elsewhere, origin)
    elsewhere["client"].set_tag(copy.info.run_id, LOGGED_THROUGH_TAG, "300")  # trained on here
    line = one_line_error(ingest(elsewhere, bundle))
    assert f"run {origin} went on where it came from (FINISHED, logged through " in line, line
    assert "was trained on too (logged through 300): two continuations of one run" in line
    assert elsewhere["client"].get_run(copy.info.run_id).info.status == "KILLED"
    assert len(all_runs(elsewhere["client"])) == 11


def test_a_run_trained_by_two_codes_travels_without_a_fingerprint(studied, tmp_path):
    """An imported run carries the fingerprint its bundle recorded; continued here by other code
    (two code digests), it no longer may: its export records none, whatever the tag says."""
    from walkers.training.provenance import CODE_DIGEST_TAG

    _, bundle, _ = studied
    here = new_store(tmp_path)
    bundles.import_bundle(here["client"], bundle)
    jobs = [r for r in all_runs(here["client"]) if r.data.tags.get("walkers.job_key")]
    assert all(bundles.FINGERPRINT_TAG in r.data.tags for r in jobs)
    resumed = jobs[0]
    digest = resumed.data.tags[CODE_DIGEST_TAG]
    here["client"].set_tag(resumed.info.run_id, CODE_DIGEST_TAG, f"{digest}+0therc0de")
    out = tmp_path / "out"
    exported(here, "study=t", f"out={out}")
    fingerprints = {r["origin"]: r["fingerprint"] for r in bundles.read_bundle(out)["runs"]}
    assert fingerprints.pop(resumed.data.tags[bundles.ORIGIN_TAG]) is None
    assert len([f for f in fingerprints.values() if f]) == len(jobs) - 1


def test_a_bad_export_is_refused_in_one_line_and_writes_nothing(studied):
    source, _, _ = studied
    before = sorted(p.name for p in source["path"].iterdir())
    line = one_line_error(export(source, "study=nope", "out=new_bundle"))
    assert "study='nope' has no run in this experiment: nothing exported" in line, line
    assert sorted(p.name for p in source["path"].iterdir()) == before


def test_the_same_export_again_says_how_to_write_it_anew_and_replace_true_does(studied, tmp_path):
    source, bundle, _ = studied
    out = tmp_path / "again"
    shutil.copytree(bundle, out)
    before = (out / bundles.RUNS_FILE).read_bytes()
    runs = bundles.read_bundle(out)["runs"]
    with pytest.raises(ConfigError) as refused:  # in-process: the CLI case above proves the line
        exported(source, "study=t", f"out={out}")
    expected = f"out='{out}' holds a bundle already: pass replace=true to write it anew"
    assert expected in str(refused.value)
    assert (out / bundles.RUNS_FILE).read_bytes() == before  # untouched
    (out / bundles.RUNS_FILE).write_bytes(b"stale")  # an earlier export, which replace swaps
    assert exported(source, "study=t", f"out={out}", "replace=true").runs == 11
    assert bundles.read_bundle(out)["runs"] == runs  # the same runs, written anew
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again"]  # no staging left beside it


def test_a_bundle_written_anew_by_later_code_keeps_the_fingerprints_of_untouched_runs(
    studied, tmp_path
):
    """Runs whose update today's code cannot fingerprint (another code digest trained them) keep
    the fingerprint their earlier bundle recorded when it is written anew, so they still stand as
    references; a run trained on since then loses it (it may be another update's now)."""
    from walkers.tracking.names import LOGGED_THROUGH_TAG
    from walkers.training.provenance import CODE_DIGEST_TAG

    _, bundle, _ = studied
    elsewhere = new_store(tmp_path)  # the runs as trained by an older commit, in its store
    bundles.import_bundle(elsewhere["client"], bundle)
    jobs = [r for r in all_runs(elsewhere["client"]) if r.data.tags.get("walkers.job_key")]
    for run in jobs:
        elsewhere["client"].delete_tag(run.info.run_id, bundles.FINGERPRINT_TAG)
        elsewhere["client"].set_tag(run.info.run_id, CODE_DIGEST_TAG, "an-older-commit")
    trained_on = jobs[0]
    elsewhere["client"].set_tag(trained_on.info.run_id, LOGGED_THROUGH_TAG, "999999")
    out = tmp_path / "results"
    shutil.copytree(bundle, out)

    exported(elsewhere, "study=t", f"out={out}", "replace=true")

    kept = {r["origin"]: r["fingerprint"] for r in bundles.read_bundle(out)["runs"]}
    earlier = {r["origin"]: r["fingerprint"] for r in bundles.read_bundle(bundle)["runs"]}
    origin = trained_on.data.tags[bundles.ORIGIN_TAG]
    assert kept.pop(origin) is None and earlier.pop(origin)
    assert kept == earlier and len([f for f in kept.values() if f]) == len(jobs) - 1


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["tracking.experiment=nope"], "tracking.experiment='nope' is not in the store"),
        (["statuses=[DONE]"], "statuses=['DONE'] is not allowed: some of FINISHED, KILLED"),
        (["study=t", "where={algo: a2c}"], "no run of 'ab_tiny' matches: nothing exported"),
        (["study=t", "where=[3]"], "where=[3] is not allowed: a mapping of tags"),
        (["study=t", "out=."], "out='.' is not empty: export into a new folder"),
        (["study=t", "replace=yes"], "replace='yes' is not allowed: true or false"),
    ],
)
def test_bad_exports_are_refused(studied, args, expected):
    """The checks ``walkers.export`` runs first (in-process: the CLI case above proves the line)."""
    source, _, _ = studied
    out = source["path"] / "new_bundle"
    cfg = compose_cfg(
        [f"tracking.uri={source['uri']}", "tracking.experiment=ab_tiny", f"out={out}", *args],
        config_name="export",
    )
    with pytest.raises(ConfigError) as refused:
        export_runs(cfg)
    assert expected in str(refused.value)
    assert not out.exists()


@pytest.mark.slow  # a second study, of 5 jobs
def test_a_study_with_a_reference_arm_trains_only_its_other_arms(studied, tmp_path):
    """The study's 'long' arm declared as the bundle's: only 'short' trains, and the answer,
    the report and the refusal of a design that needs seeds the bundle lacks follow."""
    _, bundle, _ = studied
    target = new_store(tmp_path)
    declared = arms(
        "{short:'algo=reinforce env.max_episode_steps=100',"
        f"long:{{reference:'{bundle}',arm:long}}}}"
    )
    too_many = run_cli(study(target, *declared), cwd=target["path"])  # seeds 5..7
    line = one_line_error(too_many)
    assert f"arm 'long': reference {bundle} holds no seed 5 of pendulum" in line, line
    assert all_runs(target["client"]) == []

    five = "hydra.sweeper.seeds={min:5,max:5,per_round:1}"

    def seed_held_twice(document):  # two studies' arms 'long' in one bundle, say
        record = next(r for r in document["runs"] if r["tags"].get("walkers.job_key", "")
                      .startswith("ab/t/long/pendulum/1"))  # fmt: skip
        record["tags"]["seed"] = "0"

    twice = _rewritten(bundle, tmp_path, seed_held_twice)
    line = one_line_error(run_cli(study(target, *arms(
        "{short:'algo=reinforce env.max_episode_steps=100',"
        f"long:{{reference:'{twice}',arm:long}}}}"
    ), five), cwd=target["path"]))  # fmt: skip
    assert f"arm 'long': reference {twice} holds seed 0 twice (runs " in line, line
    assert all_runs(target["client"]) == []

    result = run_cli(study(target, *declared, five), cwd=target["path"])
    assert result.returncode == 0, result.stderr[-3000:]
    trained = [r for r in all_runs(target["client"]) if "walkers.job_key" in r.data.tags]
    assert sorted(r.data.tags["walkers.job_key"] for r in trained) == [
        f"ab/t/short/pendulum/{seed}" for seed in range(5)
    ]
    assert "short is better than long on pendulum (5 seeds per arm" in result.stdout
    assert "report: reports/ab_tiny/Pendulum-v1/report.md" in result.stdout, result.stdout[-3000:]
    report = (target["path"] / "reports/ab_tiny/Pendulum-v1/report.md").read_text()
    assert "## Arms from references" in report and f"| `{bundle}` |" in report


def test_histories_travel_losslessly_and_share_their_axes():
    """float32 values as float32's shortest text, doubles as doubles', NaN and infinities as
    strings: every point comes back the same double; keys logged together share one axis."""
    import math

    import numpy as np
    from mlflow.entities import Metric

    from walkers.tracking import histories

    steps, times = (
        [0, 1000, 2000, 3000],
        [1700000000000, 1700000000500, 1700000001900, 1700000002000],
    )
    loss = [float(np.float32(x)) for x in (0.1, 1e-8, 3.4e38, -2.5)]  # a tensor's values
    ret = [-1234.5678901234567, float("nan"), float("inf"), 0.1]  # sums in float64
    given = {
        "loss/actor": [
            Metric("loss/actor", v, t, s) for s, v, t in zip(steps, loss, times, strict=True)
        ],
        "loss/critic": [
            Metric("loss/critic", -v, t, s) for s, v, t in zip(steps, loss, times, strict=True)
        ],
        "eval/return_mean": [
            Metric("eval/return_mean", v, t, s) for s, v, t in zip(steps, ret, times, strict=True)
        ],
    }
    encoded = histories.encode(given)
    assert len(encoded["axes"]) == 1  # the three share their steps and times
    assert (
        encoded["series"]["loss/actor"]["float32"]
        and "float32" not in encoded["series"]["eval/return_mean"]
    )
    back = histories.decode(json.loads(json.dumps(encoded)))
    for key, points in given.items():
        for a, b in zip(points, back[key], strict=True):
            assert (a.step, a.timestamp) == (b.step, b.timestamp)
            assert a.value == b.value or (math.isnan(a.value) and math.isnan(b.value))


def test_an_import_killed_midway_is_cleaned_up_by_the_next(studied, tmp_path):
    """kill -9 during an import leaves the run it was writing RUNNING and marked as importing
    (what a killed import leaves, made in a real store): the next import deletes it and
    imports that run whole."""
    _, bundle, _ = studied
    target = new_store(tmp_path)
    client = MlflowClient(target["uri"])
    experiment_id = get_or_create_experiment(client, "ab_tiny")
    half = client.create_run(experiment_id, tags={bundles.IMPORTING_TAG: "true"})
    client.log_param(half.info.run_id, "algo.lr", "0.001")
    done = ingest(target, bundle)
    assert done.returncode == 0 and "imported 11 runs" in done.stdout, done.stderr[-2000:]
    assert client.get_run(half.info.run_id).info.lifecycle_stage == "deleted"
    runs = all_runs(client)
    assert len(runs) == 11 and all(bundles.IMPORTING_TAG not in r.data.tags for r in runs)
    assert {r.info.status for r in runs} == {"FINISHED"}
