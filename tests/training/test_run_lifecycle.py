"""A training run's lifecycle (walkers/training/run.py): opened, reopened on resume, ended with
a status that says what can be done with it, even when opening itself fails."""

from __future__ import annotations

import shutil

import pytest

from tests.conftest import TINY, all_runs, compose_cfg, new_store, run_cli, tiny
from walkers.train import train

pytestmark = pytest.mark.faults  # `make test-faults`, beside `make test` in CI


def test_a_resume_that_fails_to_reopen_its_run_leaves_it_continuable(tmp_path):
    """The resumed run's folder cannot take its config.yaml (a directory stands in the way): the
    resume fails, the run ends KILLED, not FAILED (it can still go on), and once the way is clear
    the same command continues it."""
    store = new_store(tmp_path)
    train(compose_cfg(["algo=td3", "env=pendulum", *TINY, "algo.learning_starts=100",
                       *store["overrides"]]))  # fmt: skip
    (run,) = all_runs(store["client"])
    run_id = run.info.run_id
    config_yaml = tmp_path / "work" / "runs" / run_id / "config.yaml"
    config_yaml.unlink()
    config_yaml.mkdir()  # the fault
    resume = [f"resume={run_id}", "total_steps=900", *store["overrides"]]
    failed = run_cli(resume, cwd=tmp_path)
    assert failed.returncode != 0
    assert "IsADirectoryError" in failed.stderr
    assert store["client"].get_run(run_id).info.status == "KILLED"
    shutil.rmtree(config_yaml)
    result = run_cli(resume, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert store["client"].get_run(run_id).info.status == "FINISHED"
    steps = [m.step for m in store["client"].get_metric_history(run_id, "eval/return_mean")]
    assert steps == [300, 600, 900] and len(all_runs(store["client"])) == 1


def test_a_ctrl_c_inside_an_update_of_a_training_started_from_python_lands_after_the_step(
    store, monkeypatch
):
    """train() from Python, not through walkers.train's handler: a SIGINT right after the 149th
    Adam step (the critics' step of TD3's 100th update, whose actor step is still to come) is
    held until the step ends; the run ends KILLED with a checkpoint of whole updates at the
    agent's count of transitions, and Python's own handler is back afterwards."""
    import os
    import signal

    import torch

    from walkers.training.run import read_checkpoint

    adam_step, calls = torch.optim.Adam.step, []

    def step(self, *args, **kwargs):
        out = adam_step(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 149:
            os.kill(os.getpid(), signal.SIGINT)
        return out

    monkeypatch.setattr(torch.optim.Adam, "step", step)
    handler = signal.getsignal(signal.SIGINT)
    cfg = compose_cfg(["algo=td3", "env=pendulum", *TINY, *tiny("td3"), *store["overrides"]])
    with pytest.raises(KeyboardInterrupt):
        train(cfg)
    assert signal.getsignal(signal.SIGINT) is handler
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"])
    )
    state = read_checkpoint(path)
    assert state["trainer"]["step"] == state["agent"]["steps"] > 100
    # every update whole: one per step from the warm-up's end (100 steps, a batch of 32), the
    # critics stepped at each, the actor at every second
    updates = state["agent"]["num_updates"]
    assert updates == state["agent"]["steps"] - 100 + 1 >= 100
    adam_steps = {
        name: int(state["agent"][name]["state"][0]["step"])
        for name in ("critic_optimizer", "actor_optimizer")
    }
    assert adam_steps == {"critic_optimizer": updates, "actor_optimizer": updates // 2}
