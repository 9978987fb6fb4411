"""The reference results in ``results/``: each page's report is what its bundle gives today, to
the digit (``python -m walkers.results`` writes them; nothing there is typed by hand)."""

from __future__ import annotations

import json

import pytest

from walkers.results import RESULTS_DIR, pages, write_page


@pytest.mark.parametrize("name", pages())
def test_a_results_page_is_its_bundle_s_report(name, tmp_path):
    out = write_page(name, out=tmp_path / "report")
    committed = sorted(p.relative_to(RESULTS_DIR / name / "report") for p in
                       (RESULTS_DIR / name / "report").rglob("summary.json"))  # fmt: skip
    assert committed, f"results/{name} has no report: run python -m walkers.results {name}"
    for path in committed:
        summary = json.loads((out / path).read_text())
        assert summary == json.loads((RESULTS_DIR / name / "report" / path).read_text()), (
            f"results/{name}/report/{path} drifted from its bundle: python -m walkers.results"
        )
        if "pairs" in summary:  # an env's report pairs arms only where there are two or more
            pairwise = "## Pairwise" in (out / path.parent / "report.md").read_text()
            assert pairwise == bool(summary["pairs"]) == (len(summary["algos"]) > 1)


def test_an_unknown_page_is_refused_in_one_line():
    from walkers.errors import ConfigError

    with pytest.raises(ConfigError) as refused:
        write_page("nope")
    assert str(refused.value).startswith(f"results='nope' is not allowed: one of {pages()[0]}")
