"""The front door stays true: the README's and the docs' lists of algorithms, envs, studies and
layers are what the code declares (the algorithms' declarations, ``conf/env``, ``conf/ab``, the
import contract in ``pyproject.toml``), as ``test_docs_code.py`` keeps the quoted code true. A
new algorithm, env, study or layer fails here until the pages name it. ``make help`` fits 100
columns, and each of its targets has its long form in docs/make-targets.md."""

from __future__ import annotations

import os
import re
import subprocess
import tomllib

import pytest
from hydra.utils import get_class

from tests.conftest import PROJECT_ROOT
from walkers.agents.declarations.schemas import SCHEMAS

README = (PROJECT_ROOT / "README.md").read_text()
DOCS = PROJECT_ROOT / "docs"
ALGORITHMS = set(SCHEMAS)
ONLINE = {name for name, s in SCHEMAS.items() if not getattr(get_class(s.AGENT), "offline", False)}
ENVS = {path.stem for path in (PROJECT_ROOT / "conf" / "env").glob("*.yaml")}
STUDIES = {path.stem for path in (PROJECT_ROOT / "conf" / "ab").glob("*.yaml")}
MAKEFILE = (PROJECT_ROOT / "Makefile").read_text()
#: the targets `make help` lists: those with a `## ` summary in the Makefile
MAKE_SUMMARIES = dict(re.findall(r"^([a-zA-Z0-9_-]+):.*?## (.*)$", MAKEFILE, re.M))
MAKE_TARGETS = list(MAKE_SUMMARIES)
NUMBER_WORDS = {3: "three", 4: "four", 5: "five", 6: "six", 7: "seven", 8: "eight", 9: "nine"}


def make_help() -> list[str]:
    """The lines `make help` prints (run as a user would, not as a sub-make of `make test`)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    result = subprocess.run(
        ["make", "--no-print-directory", "help"],
        cwd=PROJECT_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout.splitlines()


def _block_after(text: str, heading: str) -> str:
    """The first fenced block after ``heading``."""
    rest = text[text.index(heading) :]
    return rest.split("```")[1]


def _backquoted_choices(text: str, key: str) -> set[str]:
    """The choices a page lists as ``\\`key\\` = \\`a\\` | \\`b\\`...`` (or with commas)."""
    found = re.search(rf"`{key}` = ((?:`\w+`(?: \(.*?\))?[ ,|\n]*(?:\| )?)+)", text)
    assert found, f"no list of {key} choices"
    return set(re.findall(r"`(\w+)`", found.group(1)))


def test_the_readme_table_has_a_row_per_declared_algorithm():
    table = README[README.index("| algorithm | paper |") :].split("\n\n")[0]
    assert set(re.findall(r"\(docs/algorithms/(\w+)\.md\)", table)) == ALGORITHMS
    for name in ALGORITHMS:
        assert (DOCS / "algorithms" / f"{name}.md").is_file(), name


def test_the_training_page_lists_every_algorithm_and_env():
    text = (DOCS / "training.md").read_text()
    assert _backquoted_choices(text, "algo") == ALGORITHMS
    assert _backquoted_choices(text, "env") == ENVS
    error = re.search(r"error: algo='a2c' is not allowed: must be one of (.*)", text).group(1)
    assert set(error.split(", ")) == ALGORITHMS  # the error example is today's error


def test_the_training_page_lists_every_study_and_the_studies_page_describes_each():
    text = (DOCS / "training.md").read_text()
    assert _backquoted_choices(text, "ab") == STUDIES
    studies = (DOCS / "studies.md").read_text()
    for name in STUDIES:
        assert f"ab={name}" in studies, f"docs/studies.md never names ab={name}"


def test_the_getting_started_count_of_online_algorithms_is_the_declared_one():
    text = (DOCS / "getting-started.md").read_text()
    counts = re.findall(r"the (\w+) online algorithms", text)
    assert counts and set(counts) == {NUMBER_WORDS[len(ONLINE)]}, counts


@pytest.mark.parametrize(
    "page, heading",
    [("README.md", "## The layers"), ("docs/architecture.md", "walkers/")],
    ids=["readme", "architecture"],
)
def test_the_layer_diagrams_name_every_layer_of_the_import_contract(page, heading):
    contract = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())
    layers = next(
        c["layers"] for c in contract["tool"]["importlinter"]["contracts"] if c["type"] == "layers"
    )
    modules = {m.strip().removeprefix("walkers.") for layer in layers for m in layer.split("|")}
    diagram = _block_after((PROJECT_ROOT / page).read_text(), heading)
    missing = sorted(m for m in modules if not re.search(rf"\b{m}\b", diagram))
    assert not missing, f"{page}'s layer diagram omits {missing}"


def test_make_help_fits_100_columns_with_a_line_per_target_and_the_options():
    lines = make_help()
    assert [line for line in lines if len(line) > 100] == []
    targets = [line for line in lines if line.startswith("  make ")]
    assert [line.split()[1] for line in targets] == MAKE_TARGETS
    for line in targets:  # each summary whole: short enough that help's cut never bites
        assert line.endswith(MAKE_SUMMARIES[line.split()[1]]), line
    footer = " ".join(line for line in lines if not line.startswith("  make "))
    assert "make install PYTHON=python3.12" in footer and 'ARGS="' in footer
    for option in re.findall(r"^([A-Z_]+) \?=", MAKEFILE, re.M):  # by name or by family (BENCH_*)
        assert option in footer or option.split("_")[0] + "_*" in footer, option


def test_the_make_targets_page_has_a_row_per_target():
    """Each target's long form: `make help` prints the short one."""
    page = (DOCS / "make-targets.md").read_text()
    assert sorted(re.findall(r"^\| `make ([\w-]+)` \|", page, re.M)) == sorted(MAKE_TARGETS)
