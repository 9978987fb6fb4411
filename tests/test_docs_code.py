"""The algorithm pages quote their code: every quote in a page's "code" column is in the file
the page names (or names another file of the project), so a change to the update that leaves its
page behind fails here."""

from __future__ import annotations

import re

import pytest

from tests.conftest import PROJECT_ROOT

PAGES = sorted((PROJECT_ROOT / "docs" / "algorithms").glob("*.md"))
ALGORITHM_PAGES = [page for page in PAGES if re.search(r"File: `", page.read_text())]


def code_column_quotes(page_text: str) -> list[str]:
    """The backquoted fragments of the last column of the page's first table whose header's
    last column is ``code``."""
    quotes, in_table = [], False
    for line in page_text.splitlines():
        cells = (
            [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else []
        )
        if cells and cells[-1] == "code":
            in_table = True
        elif in_table and not cells:
            break
        elif in_table and not set(cells[-1]) <= set("-: "):
            quotes += re.findall(r"`([^`]+)`", cells[-1])
    return quotes


@pytest.mark.parametrize("page", ALGORITHM_PAGES, ids=lambda p: p.stem)
def test_every_quote_in_the_code_column_is_in_the_named_file(page):
    text = page.read_text()
    source = PROJECT_ROOT / re.search(r"File: `([^`]+)`", text).group(1)
    code = source.read_text()
    quotes = code_column_quotes(text)
    assert len(quotes) >= 8, "the page lost its code column"
    # a quote that names a file of the project points there (`walkers/data/rollouts.py`)
    missing = [q for q in quotes if q not in code and not (PROJECT_ROOT / q).is_file()]
    assert not missing, f"{page.name} quotes lines that {source.name} no longer has: {missing}"


def test_a_quote_that_is_not_in_the_file_is_caught():
    page = ALGORITHM_PAGES[0].read_text()
    quotes = code_column_quotes(page.replace("critic_loss.sum().backward()", "loss.backward()"))
    assert "loss.backward()" in quotes
