"""``python -m walkers.results NAME``: a results page (``results/NAME/report/``) written from its
bundle by ``walkers.compare``, never by hand, so that its numbers cannot drift from its runs.

``results/NAME/`` holds ``bundle/`` (the runs: :mod:`walkers.tracking.bundles`), ``page.yaml``
(what the page is: its title, the budget reached, the machine and command that made it, and the
``walkers.compare`` overrides that make its report) and ``report/``, which this command writes
anew: the bundle's runs are compared where they lie (``walkers.compare bundle=...``).

    python -m walkers.results tiny          # or: make results
    python -m walkers.results --docs docs   # the docs site's results pages and home (make docs)

The site's home page is the README too, written at the same time with its links made the site's
(:func:`write_home`): a copy kept by hand drifted from it (its results table stopped at two pages
and its algorithm table lacked TD7).
"""

from __future__ import annotations

import re
import shutil
import sys
import tempfile
from pathlib import Path

import yaml
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from walkers import CONF_DIR, PROJECT_ROOT
from walkers.analysis.comparison import compare
from walkers.analysis.suite_report import compare_suite
from walkers.errors import ConfigError
from walkers.tracking import bundles

RESULTS_DIR = PROJECT_ROOT / "results"


def pages() -> list[str]:
    return sorted(p.parent.name for p in RESULTS_DIR.glob("*/page.yaml"))


def _check_page(name: str) -> None:
    if not (RESULTS_DIR / name / "page.yaml").is_file():
        raise ConfigError(f"results={name!r} is not allowed: one of {', '.join(pages())}")


def write_page(name: str, out: Path | None = None) -> Path:
    """Write ``results/NAME/report`` (or ``out``) from the bundle; returns the report's folder."""
    _check_page(name)
    folder = RESULTS_DIR / name
    page = yaml.safe_load((folder / "page.yaml").read_text())
    out = out or folder / "report"
    experiment = bundles.read_bundle(folder / "bundle")["source"]["experiment"]
    overrides = [
        *page["compare"],
        f"bundle={folder / 'bundle'}",
        f"tracking.experiment={experiment}",
        f"source='results/{name}/bundle (experiment {experiment})'",
        "log_report=false",
    ]
    with initialize_config_dir(config_dir=str(CONF_DIR)):
        cfg = compose("compare", overrides=overrides)
    # written beside the committed report and swapped in once whole: a comparison refused (a
    # reference no longer like for like with today's code) leaves the report as it was
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as tmp:
        with open_dict(cfg):
            cfg.out = str(Path(tmp) / "new" / "${env.id}")
        if cfg.envs:
            compare_suite(cfg)
        else:
            compare(cfg)
        if out.exists():
            out.rename(Path(tmp) / "earlier")  # removed with the staging folder
        (Path(tmp) / "new").rename(out)
    return out


def write_docs(docs: Path) -> list[Path]:
    """The documentation site's results section, from the committed reports: per page its
    metadata (``page.yaml``) and each of its reports with their plots, and an index."""
    root = Path(docs) / "results"
    if root.exists():
        shutil.rmtree(root)
    written, rows = [], []
    for name in pages():
        page = yaml.safe_load((RESULTS_DIR / name / "page.yaml").read_text())
        reports = sorted(p.parent for p in (RESULTS_DIR / name / "report").rglob("report.md"))
        for report in reports:
            target = root / name / report.name
            shutil.copytree(report, target)
            (target / "report.md").rename(target / "index.md")
        listed = [f"- [{r.name}]({r.name}/index.md)" for r in reports]
        facts = [f"- **{key}**: {page[key]}" for key in FACTS if key in page]
        text = [f"# {page['title']}", "", *facts, "", "## Reports", "", *listed, ""]
        (root / name).mkdir(parents=True, exist_ok=True)
        (root / name / "index.md").write_text("\n".join(text))
        written.append(root / name / "index.md")
        rows.append(f"| [{name}]({name}/index.md) | {page['title']} | {page.get('budget', '')} |")
    index = [
        "# Results",
        "",
        "Each page is written from its bundle in `results/` by `python -m walkers.results` "
        "(`make results`), never by hand; `tests/test_results.py` fails if one drifts.",
        "",
        "| page | what | budget reached |",
        "|---|---|---|",
        *rows,
        "",
    ]
    (root / "index.md").write_text("\n".join(index))
    return [root / "index.md", *written]


#: README links -> the site's: a docs page, a report (whose site page is index.md) and a page.yaml.
_SITE_LINKS = (
    (re.compile(r"\]\(docs/"), "]("),
    (re.compile(r"\]\((results/[^/)]+)/report/([^/)]+)/report\.md\)"), r"](\1/\2/index.md)"),
    (re.compile(r"\]\((results/[^/)]+)/page\.yaml\)"), r"](\1/index.md)"),
)
#: The README's pointer to the site, which on the site itself says where it comes from.
_README_POINTER = re.compile(r"^The full guide is the documentation site in .*$", re.M)


def write_home(docs: Path, readme: Path = PROJECT_ROOT / "README.md") -> Path:
    """The site's home page (``docs/index.md``): the README, its links rewritten for the site.
    Needs the results pages (:func:`write_docs`) that its results table links to."""
    text = readme.read_text()
    for pattern, replacement in _SITE_LINKS:
        text = pattern.sub(replacement, text)
    text = _README_POINTER.sub(
        "This site is built from `docs/` and the README by `make docs`; the README is its home "
        "page, written here unchanged but for its links.",
        text,
    )
    home = Path(docs) / "index.md"
    home.write_text(text)
    return home


#: What a results page says of itself, from its ``page.yaml``.
FACTS = ("study", "budget", "machine", "command", "commit", "date")


def main(argv: list[str]) -> int:
    if argv[:1] == ["--docs"]:
        docs = Path(argv[1] if len(argv) > 1 else "docs")
        for path in [*write_docs(docs), write_home(docs)]:
            print(path)
        return 0
    names = argv or pages()
    try:  # every name before anything is written
        for name in names:
            _check_page(name)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    failed = 0
    for name in names:  # one page refused: the others are still written
        try:
            print(f"results/{name}: {write_page(name)}")
        except ConfigError as e:
            print(f"error: results/{name}: {e}", file=sys.stderr)
            failed += 1
    return 2 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
