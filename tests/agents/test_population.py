"""population=K: seeds trained together as stacked networks, each member its own MLflow run."""

from __future__ import annotations

import signal

import numpy as np
import pytest
import torch

from tests.conftest import (
    TINY,
    all_runs,
    compose_cfg,
    feed_members,
    run_cli,
    signal_once_checkpointed,
    tiny,
)
from walkers.agents.factory import defaults_for
from walkers.agents.td3 import TD3
from walkers.errors import ConfigError
from walkers.train import train
from walkers.training.envs import make_env
from walkers.training.run import agent_from_checkpoint, read_checkpoint
from walkers.training.settings import validate

SMALL = defaults_for(
    TD3, batch_size=16, learning_starts=20, hidden_sizes=[16, 16], buffer_size=1000
)


def test_a_member_cut_out_is_an_ordinary_agent():
    population = TD3(3, [-2.0], [2.0], population=3, seed=0, **SMALL)
    feed_members(population, rewards=[0.5, 1.0, -1.0])
    single = TD3(3, [-2.0], [2.0], seed=2, **SMALL)
    single.load_state_dict(population.member_state_dict(2, with_buffer=True))
    obs = np.array([0.1, -0.3, 0.7])
    np.testing.assert_allclose(
        single.act(obs, explore=False), population.member_policy(2).act(obs), atol=1e-5
    )
    assert len(single.buffer) == 60 and single.update()  # it keeps learning on its own


def test_members_cut_out_and_loaded_back_continue_as_the_same_population():
    original = TD3(3, [-2.0], [2.0], population=3, seed=0, **SMALL)
    feed_members(original, rewards=[0.5, 1.0, -1.0])
    rebuilt = TD3(3, [-2.0], [2.0], population=3, seed=7, **SMALL)  # other seeds, fresh Adam
    for i in range(3):
        rebuilt.load_member_state_dict(i, original.member_state_dict(i, with_buffer=True))
    for agent in (original, rebuilt):  # the smoothing noise's streams came with the members
        feed_members(agent, steps=30, rewards=[0.5, 1.0, -1.0])
    for name in ("actor", "critic", "actor_target", "critic_target"):
        rebuilt_state = getattr(rebuilt, name).state_dict()
        for key, value in getattr(original, name).state_dict().items():
            assert torch.equal(value, rebuilt_state[key]), f"{name}.{key}"
    for i in range(3):  # exploration noise, buffers and Adam moments all carried over
        a, b = original.member_state_dict(i), rebuilt.member_state_dict(i)
        assert a["rng"] == b["rng"] and a["buffer"]["pos"] == b["buffer"]["pos"]
        for x, y in zip(
            a["critic_optimizer"]["state"].values(),
            b["critic_optimizer"]["state"].values(),
            strict=True,
        ):
            assert all(torch.equal(x[k], y[k]) for k in ("step", "exp_avg", "exp_avg_sq"))


def test_population_run_logs_each_member_as_its_own_run(store):
    train(
        compose_cfg(
            [
                "algo=td3",
                "env=pendulum",
                "population=2",
                "seed=5",
                *TINY,
                "algo.learning_starts=100",
                "algo.hidden_sizes=[32,32]",
                *store["overrides"],
            ]
        )
    )
    runs = sorted(all_runs(store["client"]), key=lambda r: r.data.params["seed"])
    assert [r.data.params["seed"] for r in runs] == ["5", "6"]
    assert [r.data.tags["walkers.population_member"] for r in runs] == ["0", "1"]
    client = store["client"]
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": 200}, shaping=False)
    for run in runs:
        assert run.info.status == "FINISHED" and run.data.tags["walkers.population"] == "2"
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]
        assert steps == [300, 600]
        assert {"final/return_mean", "perf/sps", "perf/population_sps", "loss/critic"} <= set(
            run.data.metrics
        )
        path = client.download_artifacts(
            run.info.run_id, "checkpoints/last.pt", str(store["path"] / run.info.run_id)
        )
        run_cfg, agent = agent_from_checkpoint(read_checkpoint(path), env, "cpu")
        assert run_cfg.seed == int(run.data.params["seed"]) and run_cfg.population == 1
        assert agent.act(env.reset(seed=0)[0], explore=False).shape == (1,)
    env.close()
    returns = [
        [m.value for m in client.get_metric_history(r.info.run_id, "train/episode_return")]
        for r in runs
    ]
    assert returns[0] != returns[1]  # different seeds, different experience
    # a member's run resumes like any run, continuing that member alone
    member = runs[1].info.run_id
    resumed = compose_cfg([f"resume={member}", "total_steps=700", *store["overrides"]])
    train(resumed, overrides=["total_steps=700"])
    assert client.get_run(member).info.status == "FINISHED"
    steps = [m.step for m in client.get_metric_history(member, "eval/return_mean")]
    assert steps == [300, 600, 700]


@pytest.mark.parametrize("algo", ["td3", "crossq"])
def test_a_member_trains_as_a_single_run_of_its_seed(store, algo):
    """Member 1 of the population of seeds (5, 6) is the run of seed 6 alone: the same initial
    weights, env starts, exploration, replay batches and update noise, so the same experiment
    to float rounding (batched matmuls of 4 members and of 2 round differently). On the CPU:
    on CUDA the kernels for 2 members and for 1 differ more, and CrossQ's batch-normalised
    critic grows that into a different third episode (an H200: -1281 against -1225); the draws
    themselves are the same on any device (tests/test_seeding.py)."""
    common = [f"algo={algo}", "env=pendulum", "device=cpu", *TINY, *tiny(algo), *store["overrides"]]
    train(compose_cfg([*common, "population=2", "seed=5"]))
    train(compose_cfg([*common, "seed=6"]))
    client = store["client"]
    runs = [r for r in all_runs(client) if r.data.params["seed"] == "6"]
    (member,) = [r for r in runs if "walkers.population_member" in r.data.tags]
    (single,) = [r for r in runs if "walkers.population_member" not in r.data.tags]

    def history(run, metric):
        return [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, metric)]

    # the member's losses are its own column of the population's, read at the same log steps
    losses = sorted(k for k in single.data.metrics if k.startswith("loss/"))
    assert losses and losses == sorted(k for k in member.data.metrics if k.startswith("loss/"))
    for metric in ("train/episode_return", "eval/return_mean", *losses):
        got, alone = history(member, metric), history(single, metric)
        assert [step for step, _ in got] == [step for step, _ in alone] and got
        np.testing.assert_allclose([v for _, v in got], [v for _, v in alone], rtol=1e-4)
    weights = []
    for run in (member, single):
        path = client.download_artifacts(
            run.info.run_id, "checkpoints/last.pt", str(store["path"] / run.info.run_id)
        )
        weights.append(read_checkpoint(path)["agent"]["actor"])
    for key, value in weights[0].items():
        torch.testing.assert_close(value, weights[1][key], rtol=1e-4, atol=1e-5)


def test_a_population_resumes_together(store):
    client, small = store["client"], ["algo.learning_starts=100", "algo.hidden_sizes=[16,16]"]
    train(
        compose_cfg(
            ["algo=ddpg", "env=pendulum", "population=2", *TINY, *small, *store["overrides"]]
        )
    )
    ids = [r.info.run_id for r in sorted(all_runs(client), key=lambda r: r.data.params["seed"])]

    def resume(run_ids: list[str], total_steps: int):
        given = [f"total_steps={total_steps}"]
        train(compose_cfg([f"resume=[{','.join(run_ids)}]", *given, *store["overrides"]]), given)

    with pytest.raises(ConfigError, match="two or more different runs"):
        resume([ids[0], ids[0]], 900)
    resume(ids, 900)
    assert len(all_runs(client)) == 2  # the same runs, continued
    for run_id, seed in zip(ids, ["0", "1"], strict=True):
        run = client.get_run(run_id)
        assert run.info.status == "FINISHED" and run.data.params["seed"] == seed
        assert run.data.tags["walkers.population"] == "2"
        evals = [m.step for m in client.get_metric_history(run_id, "eval/return_mean")]
        assert evals == [300, 600, 900]  # no step logged twice
        losses = [m.step for m in client.get_metric_history(run_id, "loss/critic")]
        assert losses == sorted(set(losses)) and losses[-1] == 900
    # Runs at different steps or of different configurations do not resume together.
    train(
        compose_cfg([f"resume={ids[1]}", "total_steps=1000", *store["overrides"]]),
        ["total_steps=1000"],
    )
    with pytest.raises(ConfigError, match="at step 900 and run .* at step 1000"):
        resume(ids, 1200)
    train(compose_cfg(["algo=td3", "env=pendulum", *TINY, *small, *store["overrides"]]))
    td3 = next(r.info.run_id for r in all_runs(client) if r.info.run_id not in ids)
    with pytest.raises(ConfigError, match="differ in algo"):
        resume([ids[0], td3], 1200)


@pytest.mark.parametrize(
    "overrides,expected",
    [
        (["algo=reinforce", "population=2"], "population=2 is not allowed with algo=reinforce"),
        (["population=2", "video_every=1000"], "population=2 is not allowed with video_every"),
        (["population=0"], "population=0 is not allowed: must be an integer > 0"),
    ],
)
def test_bad_population(overrides, expected):
    with pytest.raises(ConfigError, match=expected):
        validate(compose_cfg(overrides))


@pytest.mark.slow  # `make test-slow`
def test_a_population_job_run_again_continues_its_member_runs(store):
    """A cluster runs a job again when its worker died (kill -9): a population's job finds the
    K runs of its first attempt by its job key and continues them together, starting none."""
    args = ["algo=ddpg", "env=pendulum", "population=2", *TINY, "total_steps=1500",
            "algo.learning_starts=100", "algo.hidden_sizes=[16,16]",
            "job_key=study-3f2a/trial0/seed0", *store["overrides"]]  # fmt: skip
    code, _, _ = signal_once_checkpointed(args, store["path"], "last.pt", signal.SIGKILL)
    assert code == -signal.SIGKILL
    client = store["client"]
    first = {r.info.run_id for r in all_runs(client)}
    assert len(first) == 2 and all(r.info.status == "RUNNING" for r in all_runs(client))

    again = run_cli(args, cwd=store["path"])  # the job's second attempt: the same command
    assert again.returncode == 0, again.stderr[-3000:]
    log = again.stdout + again.stderr
    assert "ran before as run(s)" in log  # the second attempt found the first one's runs
    runs = all_runs(client)
    if "continuing it" in log:  # continued, not duplicated
        assert {r.info.run_id for r in runs} == first
    else:  # killed between the members' checkpoints: they cannot go on together from one step
        assert "marked FAILED; starting anew" in log
        superseded = [r for r in runs if "walkers.superseded" in r.data.tags]
        assert {r.info.run_id for r in superseded} == first
        assert all(r.info.status == "FAILED" for r in superseded)
        runs = [r for r in runs if r.info.run_id not in first]
    assert len(runs) == 2
    for run in runs:
        assert run.info.status == "FINISHED"
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/return_mean")]
        assert steps == sorted(set(steps)) and steps[-1] == 1500  # none twice, to the end

    third = run_cli(args, cwd=store["path"])  # once more, after it finished: nothing to train
    assert third.returncode == 0 and "nothing to train" in third.stdout, third.stderr[-2000:]
    assert {r.info.run_id for r in all_runs(client)} == {r.info.run_id for r in runs} | (
        first if "starting anew" in log else set()
    )


@pytest.mark.slow  # `make test-slow`: trains every seed twice over
def test_seeds_that_finished_alone_leave_their_population_job_nothing_to_train(store):
    """A job key and run name with {seed} in them name each run by its own seed, alone or as a
    member (make baseline's keys): once seeds 0 and 1 finished as single runs, the population
    job of seeds 0-1 finds them and trains nothing, and the other way round."""
    keyed = ['job_key="keyed/{seed}"', 'tracking.run_name="keyed-s{seed}"']
    common = ["algo=td3", "env=pendulum", *TINY, *tiny("td3"), *keyed, *store["overrides"]]
    alone = run_cli(["-m", "seed=0,1", *common], cwd=store["path"])
    assert alone.returncode == 0, alone.stderr[-3000:]
    runs = all_runs(store["client"])
    assert sorted(r.info.run_name for r in runs) == ["keyed-s0", "keyed-s1"]
    assert sorted(r.data.tags["walkers.job_key"] for r in runs) == ["keyed/0", "keyed/1"]

    together = run_cli(["population=2", "seed=0", *common], cwd=store["path"])
    assert together.returncode == 0, together.stderr[-3000:]
    assert "already FINISHED as run(s)" in together.stdout
    assert len(all_runs(store["client"])) == 2  # nothing trained again
    alone_again = run_cli(["seed=1", *common], cwd=store["path"])
    assert alone_again.returncode == 0 and "nothing to train" in alone_again.stdout
    assert len(all_runs(store["client"])) == 2
