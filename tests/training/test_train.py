"""Real tiny trainings into temporary MLflow stores."""

from __future__ import annotations

import pytest

from tests.conftest import TINY, all_runs, compose_cfg, metric_steps, run_cli
from walkers.train import train
from walkers.training.run import read_checkpoint

TRAIN_METRICS = {"train/episode_return", "train/episode_length", "perf/sps"}
EVAL_METRICS = {"eval/return_mean", "eval/return_std"}
FINAL_METRICS = {
    "final/return_mean",
    "final/return_last10",
    "final/auc",
    "final/steps_to_threshold",
}


@pytest.mark.parametrize(
    "env,budget",
    [
        ("pendulum", ["algo.learning_starts=200"]),
        ("walker2d", ["algo.learning_starts=200", "algo.batch_size=32"]),
    ],
)
def test_tiny_td3_run_is_fully_logged(store, env, budget):
    cfg = compose_cfg([f"env={env}", "algo=td3", "seed=1", *TINY, *budget, *store["overrides"]])
    value = train(cfg)

    (run,) = all_runs(store["client"])
    client = store["client"]
    assert run.info.status == "FINISHED"
    assert value == pytest.approx(run.data.metrics["final/return_last10"])
    assert {"algo.lr", "algo.hidden_sizes", "env.id", "seed", "total_steps"} <= set(run.data.params)
    assert run.data.params["algo.hidden_sizes"] == "[256, 256]"
    assert {"algo", "env", "seed", "git_commit"} <= set(run.data.tags)
    assert run.data.tags["algo"] == "td3" and run.data.tags["seed"] == "1"
    assert TRAIN_METRICS | EVAL_METRICS | FINAL_METRICS | {"loss/critic", "loss/actor"} <= set(
        run.data.metrics
    )
    assert metric_steps(client, run.info.run_id, "eval/return_mean") == [300, 600]
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id, "checkpoints")}
    assert artifacts == {"checkpoints/last.pt", "checkpoints/best.pt"}
    assert "config.yaml" in {a.path for a in client.list_artifacts(run.info.run_id)}

    last = read_checkpoint(
        client.download_artifacts(run.info.run_id, "checkpoints/last.pt", str(store["path"]))
    )
    assert last["trainer"]["step"] == 600
    assert last["agent"]["steps"] == 600
    assert set(last["agent"]) >= {"actor", "critic", "actor_optimizer", "critic_optimizer", "rng"}
    assert last["config"]["env"]["id"] == cfg.env.id


def test_same_seed_same_evaluations_on_cpu(store):
    overrides = ["env=pendulum", "seed=7", "algo.learning_starts=200", *TINY, *store["overrides"]]
    first = train(compose_cfg(overrides))
    # the same command again would train nothing (its run FINISHED): a run of another name
    second = train(compose_cfg([*overrides, "tracking.run_name=again"]))
    assert first == second
    runs = all_runs(store["client"])
    histories = [
        [m.value for m in store["client"].get_metric_history(r.info.run_id, "eval/return_mean")]
        for r in runs
    ]
    assert histories[0] == histories[1] and len(histories[0]) == 2
    other = train(compose_cfg([o.replace("seed=7", "seed=8") for o in overrides]))
    assert other != first


def test_steps_to_threshold_is_infinite_when_never_reached(store):
    cfg = compose_cfg(["env=pendulum", "env.threshold=0", *TINY, *store["overrides"]])
    train(cfg)
    (run,) = all_runs(store["client"])
    assert run.data.metrics["final/steps_to_threshold"] > 1e300  # MLflow stores inf as max float
    cfg = compose_cfg(["env=pendulum", "env.threshold=-1e6", *TINY, *store["overrides"]])
    train(cfg)
    reached = [r for r in all_runs(store["client"]) if r.info.run_id != run.info.run_id][0]
    assert reached.data.metrics["final/steps_to_threshold"] == 300


@pytest.mark.slow  # `make test-slow`
def test_resume_continues_the_same_run_without_duplicate_steps(store):
    base = ["env=pendulum", "seed=3", "algo.learning_starts=200", *TINY[1:], *store["overrides"]]
    first = run_cli(["total_steps=600", *base], cwd=store["path"])
    assert first.returncode == 0, first.stderr
    (run,) = all_runs(store["client"])
    run_id = run.info.run_id
    assert run_id in first.stdout + first.stderr  # the run id is printed at the end

    again = run_cli(
        [f"resume={run_id}", "total_steps=1200", *store["overrides"]], cwd=store["path"]
    )
    assert again.returncode == 0, again.stderr
    (run,) = all_runs(store["client"])  # still one run: the same one, continued
    assert run.info.status == "FINISHED"
    evals = metric_steps(store["client"], run_id, "eval/return_mean")
    assert evals == [300, 600, 900, 1200]
    losses = metric_steps(store["client"], run_id, "loss/critic")
    assert len(losses) == len(set(losses))
    path = store["client"].download_artifacts(run_id, "checkpoints/last.pt", str(store["path"]))
    state = read_checkpoint(path)
    assert state["trainer"]["step"] == 1200 and state["agent"]["steps"] == 1200
    assert state["trainer"]["eval_steps"] == [300, 600, 900, 1200]
