"""A terminated run ends KILLED with a checkpoint it can resume from."""

from __future__ import annotations

import signal

from tests.conftest import all_runs, run_cli, signal_once_checkpointed
from walkers.training import checkpoints

#: A run far longer than any test waits: it is stopped by a signal after its first evaluation.
LONG_RUN = [
    "env=pendulum",
    "total_steps=100000",
    "eval_every=500",
    "eval_episodes=1",
    "checkpoint_every=100000",
    "algo.learning_starts=100",
    "progress=false",
]


def test_sigterm_saves_a_checkpoint_and_ends_killed(store):
    args = [*LONG_RUN, *store["overrides"]]
    code, _, stderr = signal_once_checkpointed(args, store["path"], "best.pt", signal.SIGTERM)
    assert code == 130, stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    step = checkpoints.load(path)["trainer"]["step"]
    assert 500 <= step < 100000

    resumed = run_cli(
        [f"resume={run.info.run_id}", f"total_steps={step + 200}", *store["overrides"]],
        cwd=store["path"],
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"


def test_a_terminated_population_resumes_together(store):
    args = [*LONG_RUN, "population=2", "algo.hidden_sizes=[16,16]", *store["overrides"]]
    code, stdout, stderr = signal_once_checkpointed(args, store["path"], "best.pt", signal.SIGTERM)
    assert code == 130, stderr[-2000:]
    runs = sorted(all_runs(store["client"]), key=lambda r: r.data.params["seed"])  # member order
    assert [r.info.status for r in runs] == ["KILLED", "KILLED"]
    steps = {
        checkpoints.load(
            store["client"].download_artifacts(
                r.info.run_id, "checkpoints/last.pt", str(store["path"] / r.info.run_id)
            )
        )["trainer"]["step"]
        for r in runs
    }
    assert len(steps) == 1  # both members stopped at the same step
    (step,) = steps
    ids = ",".join(r.info.run_id for r in runs)
    assert f"resume=[{ids}]" in stdout  # the command that continues them is printed

    resumed = run_cli(
        [f"resume=[{ids}]", f"total_steps={step + 200}", *store["overrides"]], cwd=store["path"]
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert [r.info.status for r in all_runs(store["client"])] == ["FINISHED", "FINISHED"]
