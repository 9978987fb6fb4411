"""Seeds are independent samples; a resumed run is the experiment it would have been.

- No two seeds share a training or an evaluation start state; one seed reproduces its own.
- An interrupted run resumes with its replay buffer (kept in the local resume checkpoint), and
  says how to resume it; without the buffer it says so and refills before updating again.
"""

from __future__ import annotations

import shutil
import signal

import numpy as np
import pytest
import torch

from tests.conftest import PPO_TINY, TINY, all_runs, compose_cfg, run_cli, signal_once_checkpointed
from walkers.seeding import (
    env_rng_state,
    eval_start_seeds,
    first_training_reset,
    restore_env_rng,
)
from walkers.training.envs import make_env
from walkers.training.run import read_checkpoint

pytestmark = pytest.mark.slow  # `make test-slow`, beside `make test` in CI

SEEDS = range(5)
EPISODES = 30


def training_start_states(seed: int, episodes: int = EPISODES) -> list[bytes]:
    """The first observations of a run's first ``episodes`` training episodes (as the trainer
    resets: seeded once, then the env's own RNG)."""
    env = make_env(compose_cfg(["env=pendulum"]).env)
    starts = [first_training_reset(env, seed)[0].tobytes()]
    starts += [env.reset()[0].tobytes() for _ in range(episodes - 1)]
    env.close()
    return starts


def eval_start_states(seed: int, episodes: int = 10) -> list[bytes]:
    env = make_env(compose_cfg(["env=pendulum"]).env, shaping=False)
    starts = [env.reset(seed=s)[0].tobytes() for s in eval_start_seeds(seed, episodes)]
    env.close()
    return starts


def test_no_two_seeds_share_a_start_state_and_each_seed_reproduces_its_own():
    per_seed = {s: set(training_start_states(s)) | set(eval_start_states(s)) for s in SEEDS}
    for a in SEEDS:
        assert len(per_seed[a]) == EPISODES + 10  # no repeats within a run either
        for b in SEEDS:
            if a < b:
                assert not per_seed[a] & per_seed[b], (a, b)
    assert training_start_states(3) == training_start_states(3)
    assert eval_start_states(3) == eval_start_states(3)


def test_a_restored_env_rng_draws_the_start_states_the_uninterrupted_run_would_have():
    env = make_env(compose_cfg(["env=pendulum"]).env)
    first_training_reset(env, 7)
    env.reset()
    saved = env_rng_state(env)
    expected = [env.reset()[0] for _ in range(3)]
    fresh = make_env(compose_cfg(["env=pendulum"]).env)
    restore_env_rng(fresh, saved)
    assert np.array_equal(np.stack(expected), np.stack([fresh.reset()[0] for _ in range(3)]))


#: A TD3 run far longer than any test waits: signalled once it has written a checkpoint.
LONG_TD3 = [
    "algo=td3",
    "env=pendulum",
    "algo.hidden_sizes=[16,16]",
    "algo.batch_size=64",
    "total_steps=100000",
    "eval_every=300",
    "eval_episodes=1",
    "checkpoint_every=100000",
    "progress=false",
]


def _interrupt(store, extra: list[str]) -> tuple[str, dict, str]:
    """A run SIGTERM'd after its first evaluation: (run id, its local resume state, stdout)."""
    code, stdout, stderr = signal_once_checkpointed(
        [*LONG_TD3, *extra, *store["overrides"]], store["path"], "best.pt", signal.SIGTERM
    )
    assert code == 130, stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
    run_id = run.info.run_id
    local = store["path"] / "work" / "runs" / run_id / "resume" / "last.pt"
    return run_id, read_checkpoint(local), stdout


def _final_state(store, run_id: str) -> dict:
    path = store["client"].download_artifacts(
        run_id, "checkpoints/last.pt", str(store["path"] / "final")
    )
    return read_checkpoint(path)


def test_an_interrupted_run_resumes_with_its_replay_buffer(store):
    run_id, interrupted, stdout = _interrupt(store, ["algo.learning_starts=100"])
    assert f"resume={run_id}" in stdout  # the command that continues it is printed
    buffer = interrupted["agent"]["buffer"]
    n = buffer["size"]
    assert n == interrupted["agent"]["steps"] > 100  # every transition so far, kept locally
    uploaded = _final_state(store, run_id)
    assert "data" not in uploaded["agent"]["buffer"]  # MLflow's copy stays light by default

    step = interrupted["trainer"]["step"]
    resumed = run_cli(
        [f"resume={run_id}", f"total_steps={step + 100}", "save_buffer=true", *store["overrides"]],
        cwd=store["path"],
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "without the replay buffer" not in resumed.stdout + resumed.stderr
    final = _final_state(store, run_id)
    data, before = final["agent"]["buffer"]["data"], buffer["data"]
    for name, values in before.items():  # the resumed buffer starts as the interrupted one
        assert torch.equal(data[name][:n], values), name
    assert final["agent"]["buffer"]["size"] == n + 100
    assert final["agent"]["num_updates"] == interrupted["agent"]["num_updates"] + 100
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED" and "walkers.buffer_refill" not in run.data.tags
    spent = interrupted["trainer"]["cpu_seconds"]  # the CPU time counts on across the resume
    assert 0 < spent / 3600 < run.data.metrics["final/cpu_hours"]
    assert run.data.metrics["final/cpu_hours"] <= final["trainer"]["cpu_seconds"] / 3600


@pytest.mark.parametrize(
    "learning_starts,expected",
    [(100, "current policy with noise"), (5000, "uniform random: the warm-up again")],
    ids=["after-warm-up", "in-warm-up"],
)
def test_a_resume_without_the_buffer_says_so_and_refills_before_updating(
    store, learning_starts, expected
):
    run_id, interrupted, _ = _interrupt(store, [f"algo.learning_starts={learning_starts}"])
    shutil.rmtree(store["path"] / "work" / "runs" / run_id / "resume")  # e.g. another machine
    (uploaded,) = (store["path"] / "mlartifacts").rglob(f"{run_id}/**/checkpoints/last.pt")
    older = read_checkpoint(uploaded)  # and from an older walkers, which counted no CPU time
    del older["trainer"]["cpu_seconds"]
    torch.save(older, uploaded)
    agent = interrupted["agent"]
    refill = max(learning_starts, 64)  # max(learning_starts, batch_size)
    extra = 150 if learning_starts == 100 else 100
    resumed = run_cli(
        [f"resume={run_id}", f"total_steps={interrupted['trainer']['step'] + extra}"]
        + store["overrides"],
        cwd=store["path"],
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    log = resumed.stdout + resumed.stderr
    assert "without the replay buffer" in log and expected in log
    final = _final_state(store, run_id)["agent"]
    # updates again only once `refill` transitions are in: at agent steps steps0 + refill ...
    first_update = agent["steps"] + refill
    expected_updates = max(0, final["steps"] - first_update + 1)
    assert final["num_updates"] - agent["num_updates"] == expected_updates
    assert final["buffer"]["size"] == final["steps"] - agent["steps"]  # refilled from empty
    (run,) = all_runs(store["client"])
    refilled = f"steps {agent['steps']}-{first_update} ({expected})"
    assert run.data.tags["walkers.buffer_refill"] == refilled
    assert np.isnan(run.data.metrics["final/cpu_hours"])  # unknown, never a partial count


def test_a_learning_rate_warm_up_longer_than_the_run_is_pointed_out(caplog):
    from walkers.training.settings import warn_short_warmup

    warn_short_warmup(compose_cfg(["algo=dt", "env=pendulum", "total_steps=1500"]))
    (record,) = [r for r in caplog.records if "algo.warmup_steps" in r.getMessage()]
    assert (
        "algo.warmup_steps=10000" in record.getMessage()
        and "total_steps=1500" in record.getMessage()
    )
    caplog.clear()
    warn_short_warmup(compose_cfg(["algo=dt", "env=pendulum", "total_steps=20000"]))
    assert not [r for r in caplog.records if "algo.warmup_steps" in r.getMessage()]


def test_a_run_from_before_a_hyperparameter_existed_resumes_with_its_declared_default(store):
    """A checkpoint's config written before ``algo.num_envs`` was declared (PPO's 1M baselines
    were) resumes with the declared default, the behaviour it had, and the log says so."""
    first = run_cli(
        ["algo=ppo", "env=pendulum", *TINY, *PPO_TINY, *store["overrides"]],
        cwd=store["path"],
    )
    assert first.returncode == 0, first.stderr[-2000:]
    (run,) = all_runs(store["client"])
    local = store["path"] / "work" / "runs" / run.info.run_id / "resume" / "last.pt"
    older = read_checkpoint(local)
    del older["config"]["algo"]["num_envs"]  # as an older walkers wrote it
    torch.save(older, local)
    resumed = run_cli(
        [f"resume={run.info.run_id}", "total_steps=900", *store["overrides"]], cwd=store["path"]
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "predates algo.num_envs=1: resumed with the declared default" in resumed.stdout
    assert "Downloading artifacts" not in resumed.stderr  # MLflow's progress bars, silenced
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    assert _final_state(store, run.info.run_id)["trainer"]["step"] == 900


def test_a_run_resumed_by_other_update_code_no_longer_stands_as_a_reference(store, tmp_path):
    """A run whose earlier steps another walkers.agents/walkers.data trained (its code digest
    tag is not today's) records both digests when resumed, says so in one line, and its export
    carries no update fingerprint, so a comparison refuses it as a reference arm."""
    from walkers.analysis.references import check_like_for_like, load_references
    from walkers.errors import ConfigError
    from walkers.tracking import bundles
    from walkers.training.provenance import CODE_DIGEST_TAG, code_digest

    first = run_cli(["algo=td3", "env=pendulum", *TINY, *store["overrides"]], cwd=store["path"])
    assert first.returncode == 0, first.stderr[-2000:]
    (run,) = all_runs(store["client"])
    store["client"].set_tag(run.info.run_id, CODE_DIGEST_TAG, "0lderc0de")  # trained before
    resumed = run_cli(
        [f"resume={run.info.run_id}", "total_steps=900", *store["overrides"]], cwd=store["path"]
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    said = f"code digests 0lderc0de then {code_digest()}): its results stand, but it cannot"
    assert said in resumed.stdout + resumed.stderr
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    assert run.data.tags[CODE_DIGEST_TAG] == f"0lderc0de+{code_digest()}"
    assert run.data.tags["walkers.total_steps"] == "900"  # its param stays 600

    exported = run_cli(
        ["tracking.experiment=walkers", f"out={tmp_path / 'b'}", *store["overrides"][:1]],
        cwd=store["path"],
        module="walkers.export",
    )
    assert exported.returncode == 0, exported.stderr[-2000:]
    (record,) = bundles.read_bundle(tmp_path / "b")["runs"]
    assert record["fingerprint"] is None
    (reference,) = load_references([tmp_path / "b"])
    with pytest.raises(ConfigError, match="was trained by 2 codes in turn"):
        check_like_for_like(reference, "Pendulum-v1", "final/return_mean", None, None)
