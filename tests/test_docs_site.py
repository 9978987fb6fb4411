"""The documentation site, built with --strict and served, renders in a real headless Chromium
(`make ui-check`): the landing page, an algorithm page and a results page, with their tables
and images."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
import urllib.parse
import urllib.request

import pytest

from tests.browser_kit import dom
from tests.cluster_kit import free_port
from tests.conftest import PROJECT_ROOT

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """``make docs``'s build into a temporary folder, served over loopback."""
    docs = tmp_path_factory.mktemp("docs")
    shutil.copytree(PROJECT_ROOT / "docs", docs / "docs", ignore=shutil.ignore_patterns("results"))
    shutil.copy(PROJECT_ROOT / "mkdocs.yml", docs / "mkdocs.yml")
    subprocess.run([sys.executable, "-m", "walkers.results", "--docs", str(docs / "docs")],
                   check=True, capture_output=True)  # fmt: skip
    build = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-q"],
        cwd=docs,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert build.returncode == 0, build.stderr[-3000:]
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
        cwd=docs / "site",
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    for _ in range(100):
        try:
            urllib.request.urlopen(base, timeout=1)
            break
        except OSError:
            time.sleep(0.1)
    yield base
    server.terminate()
    server.wait(timeout=10)


def images_load(base: str, page: str, html: str) -> list[str]:
    """The page's <img> sources that the server serves (each fetched)."""
    sources = re.findall(r'<img[^>]+src="([^"]+)"', html)
    for src in sources:
        url = urllib.parse.urljoin(f"{base}/{page}", src)
        assert urllib.request.urlopen(url, timeout=5).status == 200, url
    return sources


@pytest.mark.parametrize(
    ("page", "expected", "images"),
    [
        ("", ["The algorithms", "CrossQ", "Set-up: two commands", "A worked A/B example"], 0),
        ("algorithms/td3/", ["The update, beside the code", "skip_nonfinite", "policy_delay"], 0),
        ("results/tiny/suite/", ["Aggregates (normalized)", "reinforce", "td3"], 2),
    ],
)
def test_a_page_renders_with_its_tables_and_images(site, page, expected, images):
    html = dom(f"{site}/{page}")
    for text in expected:
        assert text in html, (page, text)
    assert "<table" in html
    assert len(images_load(site, page, html)) >= images
