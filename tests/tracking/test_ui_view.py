"""The links walkers prints open MLflow's Model-training view, checked in a real headless
Chromium (`make ui-check`; MLflow 3.17 opens an experiment as a GenAI application otherwise)."""

from __future__ import annotations

import re

import pytest

from tests.browser_kit import dom
from tests.cluster_kit import free_port
from tests.conftest import run_cli
from walkers.tracking.servers import start_mlflow_server

pytestmark = pytest.mark.browser

#: What each view's sidebar and breadcrumb show (MLflow 3.17.2).
TRAINING_VIEW = ("Model registry",)
GENAI_VIEW = ("Evaluation runs", "Judges")


def test_the_printed_links_open_the_training_view(store):
    result = run_cli(
        ["env=pendulum", "total_steps=200", "eval_every=100", "eval_episodes=1",
         "progress=false", *store["overrides"]],
        cwd=store["path"],
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    printed = re.search(r"then (http://127\.0\.0\.1:5000/\S+)", result.stdout + result.stderr)
    assert printed and printed.group(1).endswith("?workflowType=machine_learning")
    port = free_port()
    server = start_mlflow_server(
        store["uri"], store["path"] / "mlartifacts", port, log_dir=store["path"], workers=1
    )
    try:
        link = printed.group(1).replace(":5000/", f":{port}/")
        page = dom(link)
        assert all(word in page for word in TRAINING_VIEW), page[-3000:]
        assert not any(word in page for word in GENAI_VIEW)
        # the same run without the query: MLflow's GenAI view, which is why walkers adds it
        plain = dom(link.removesuffix("?workflowType=machine_learning"))
        assert all(word in plain for word in GENAI_VIEW), plain[-3000:]
    finally:
        server.stop()
