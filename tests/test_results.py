"""The reference results in ``results/``: each page's report is what its bundle gives today, to
the digit (``python -m walkers.results`` writes them; nothing there is typed by hand)."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from tests.conftest import PROJECT_ROOT, run_cli
from walkers.results import RESULTS_DIR, pages, write_docs, write_home, write_page


@pytest.mark.parametrize("name", pages())
def test_a_results_page_is_its_bundle_s_report(name, tmp_path):
    out = write_page(name, out=tmp_path / "report")
    committed = sorted(p.relative_to(RESULTS_DIR / name / "report") for p in
                       (RESULTS_DIR / name / "report").rglob("summary.json"))  # fmt: skip
    assert committed, f"results/{name} has no report: run python -m walkers.results {name}"
    for path in committed:
        summary = json.loads((out / path).read_text())
        differ = differences(
            json.loads((RESULTS_DIR / name / "report" / path).read_text()), summary
        )
        assert not differ, (
            f"results/{name}/report/{path}: {len(differ)} values differ from what its bundle "
            f"gives today ({'; '.join(differ[:3])}). A change that moved a published figure "
            f"should not have, unless on purpose: then write the page anew with `make results "
            f"ARGS={name}` and commit it with the change"
        )
        if "pairs" in summary:  # an env's report pairs arms only where there are two or more
            pairwise = "## Pairwise" in (out / path.parent / "report.md").read_text()
            assert pairwise == bool(summary["pairs"]) == (len(summary["algos"]) > 1)


def differences(committed, now, where: str = "") -> list[str]:
    """Where two JSON values differ: ``key.path: committed -> now``, one line each."""
    if isinstance(committed, dict) and isinstance(now, dict):
        return [
            line
            for key in sorted(committed.keys() | now.keys(), key=str)
            for line in differences(committed.get(key), now.get(key), f"{where}.{key}".strip("."))
        ]
    if isinstance(committed, list) and isinstance(now, list) and len(committed) == len(now):
        return [
            line
            for i, (a, b) in enumerate(zip(committed, now, strict=True))
            for line in differences(a, b, f"{where}[{i}]")
        ]
    return [] if committed == now else [f"{where}: {committed!r} -> {now!r}"]


def test_the_drift_check_names_each_value_that_moved():
    committed = {"algos": {"td3": {"cpu_hours": 0.6956690566658333, "seeds": 6}}, "x": [1, 2]}
    now = {"algos": {"td3": {"cpu_hours": 0.6956690566658332, "seeds": 6}}, "x": [1, 3]}
    assert differences(committed, now) == [
        "algos.td3.cpu_hours: 0.6956690566658333 -> 0.6956690566658332",
        "x[1]: 2 -> 3",
    ]
    assert differences(committed, committed) == []


def test_an_unknown_page_is_refused_in_one_line():
    from walkers.errors import ConfigError

    with pytest.raises(ConfigError) as refused:
        write_page("nope")
    assert str(refused.value).startswith(f"results='nope' is not allowed: one of {pages()[0]}")


def test_a_page_whose_report_is_refused_keeps_it_and_the_other_pages_are_written(
    tmp_path, monkeypatch, capsys
):
    """``make results`` after a change that makes one page's comparison refuse (its reference
    no longer like for like, say): that page's committed report stays as it was, the others are
    written, and the command fails naming the page."""
    import walkers.results as results

    for name in ("ppo_hopper", "ppo_half_cheetah"):
        shutil.copytree(RESULTS_DIR / name, tmp_path / name)
    page = tmp_path / "ppo_hopper" / "page.yaml"
    page.write_text(
        page.read_text().replace('compare: ["env=hopper"]', 'compare: ["env=walker2d"]')
    )
    report = tmp_path / "ppo_hopper" / "report"
    before = {p: p.read_bytes() for p in report.rglob("*") if p.is_file()}
    shutil.rmtree(tmp_path / "ppo_half_cheetah" / "report")
    monkeypatch.setattr(results, "RESULTS_DIR", tmp_path)

    assert results.main([]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: results/ppo_hopper: ") and "Walker2d-v5" in error, error
    assert {p: p.read_bytes() for p in report.rglob("*") if p.is_file()} == before
    written = tmp_path / "ppo_half_cheetah" / "report" / "HalfCheetah-v5" / "summary.json"
    assert written.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ppo_half_cheetah", "ppo_hopper"]
    assert sorted(p.name for p in (tmp_path / "ppo_hopper").iterdir()) == [
        "bundle",
        "page.yaml",
        "report",
    ]  # no staging left


def test_the_sites_home_is_the_readme_with_every_link_reaching_a_site_page(tmp_path):
    """``make docs`` writes the site's home from the README (a hand-kept copy drifted): the same
    text, and each of its links a page the site holds, a results report included."""
    docs = tmp_path / "docs"
    shutil.copytree(PROJECT_ROOT / "docs", docs, ignore=shutil.ignore_patterns("results"))
    (docs / "index.md").unlink(missing_ok=True)  # the one make docs wrote, if it ran here
    write_docs(docs)
    home = write_home(docs).read_text()

    readme = (PROJECT_ROOT / "README.md").read_text()
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", home)
    assert len(links) == len(re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", readme)) > 20
    missing = [
        link for link in links if not link.startswith("http") and not (docs / link).is_file()
    ]
    assert not missing, f"README links with no page on the site: {missing}"
    strip = re.compile(r"\]\([^)]*\)")  # the text, links aside, is the README's
    assert strip.sub("]", home).splitlines()[10:] == strip.sub("]", readme).splitlines()[10:]


@pytest.mark.slow  # `make test-slow`: two bundles in, a study's report (about 2 minutes)
def test_the_ended_original_study_answers_from_its_committed_bundle_without_training(store):
    """A new machine's `make study-original` (its recipe's steps, in a fresh store): REINFORCE's
    arm and the ended study come in from `results/`, and the study command answers at once with
    the committed verdict: no job is launched, the study's report is written."""
    from tests.study_kit import ingest

    for bundle in ("reinforce_walker2d", "original"):
        done = ingest(store, RESULTS_DIR / bundle / "bundle")
        assert done.returncode == 0, done.stderr[-2000:]
    result = run_cli(
        ["-m", "ab=original", *store["overrides"], f"hydra.sweep.dir={store['path']}/multirun"],
        cwd=store["path"],
    )
    out = result.stdout + result.stderr
    assert result.returncode == 0, out[-3000:]
    assert "launching" not in out, out[-3000:]
    committed = json.loads(
        (RESULTS_DIR / "original" / "report" / "Walker2d-v5" / "summary.json").read_text()
    )
    written = json.loads(
        (store["path"] / "reports" / "ab_original" / "Walker2d-v5" / "summary.json").read_text()
    )
    assert written["algos"] == committed["algos"]
