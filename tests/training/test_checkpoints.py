"""Checkpoints are atomic and verified: a damaged file is a clear error, never a silent restart."""

from __future__ import annotations

import signal

import pytest
import torch

from tests.conftest import all_runs, compose_cfg, run_cli, signal_once_checkpointed
from walkers.errors import CheckpointError
from walkers.train import train
from walkers.training.run import read_checkpoint, write_checkpoint


def test_round_trip_and_no_temp_files_left(tmp_path):
    path = write_checkpoint({"weights": torch.arange(5)}, tmp_path / "last.pt")
    assert torch.equal(read_checkpoint(path)["weights"], torch.arange(5))
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]
    # a write killed mid-way (SIGKILL: no cleanup runs) left its temporary file: the next one goes
    (tmp_path / ".last.pt.9pqojf4h.tmp").write_bytes(b"half a checkpoint")
    (tmp_path / ".best.pt.x.tmp").write_bytes(b"another checkpoint's, being written")
    write_checkpoint({"weights": torch.arange(6)}, tmp_path / "last.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".best.pt.x.tmp", "last.pt"]


@pytest.mark.parametrize("damage", ["truncate", "garbage", "not_walkers", "missing"])
def test_damaged_checkpoint_is_a_clear_error_naming_the_file(tmp_path, damage):
    path = write_checkpoint({"weights": torch.zeros(1000)}, tmp_path / "last.pt")
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:500])
    elif damage == "garbage":
        path.write_bytes(b"\x00not a checkpoint" * 10)
    elif damage == "not_walkers":
        torch.save({"some": "dict"}, path)
    else:
        path.unlink()
    with pytest.raises(CheckpointError) as error:
        read_checkpoint(path)
    assert str(path) in str(error.value)


@pytest.mark.faults
def test_kill_9_then_resume_finishes_at_the_right_step(store):
    args = [
        "env=pendulum",
        "total_steps=1200",
        "eval_every=200",
        "eval_episodes=1",
        "checkpoint_every=200",
        "algo.learning_starts=100",
        "progress=false",
        *store["overrides"],
    ]
    signal_once_checkpointed(args, store["path"], "last.pt", signal.SIGKILL)  # no clean-up
    (run,) = all_runs(store["client"])
    resumed = run_cli([f"resume={run.info.run_id}", *store["overrides"]], cwd=store["path"])
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    assert read_checkpoint(path)["trainer"]["step"] == 1200
    evals = [
        m.step for m in store["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    ]
    assert evals == list(range(200, 1201, 200))  # none missing, none twice


def test_resume_from_a_corrupted_checkpoint_is_refused(store):
    train(  # in-process; the resume that refuses it runs as a user runs it
        compose_cfg(
            ["env=pendulum", "total_steps=400", "eval_every=200", "eval_episodes=1",
             "checkpoint_every=200", "algo.learning_starts=100", "progress=false",
             *store["overrides"]]
        )
    )  # fmt: skip
    (run,) = all_runs(store["client"])
    artifact_dir = store["path"] / "mlartifacts"
    (stored,) = [p for p in artifact_dir.rglob("last.pt") if run.info.run_id in str(p)]
    stored.write_bytes(stored.read_bytes()[:1000])
    again = run_cli(
        [f"resume={run.info.run_id}", "total_steps=600", *store["overrides"]], cwd=store["path"]
    )
    assert again.returncode == 2
    assert "corrupted or truncated" in again.stderr and "last.pt" in again.stderr
    assert all_runs(store["client"])[0].info.status == "FINISHED"  # untouched
