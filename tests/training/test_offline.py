"""Offline RL end to end: datasets recorded from the platform's own agents, a Decision Transformer
trained on them, and DT runs beside TD3 in the A/B report.

One module-scoped chain, each step real: TD3 learns Pendulum (its learning test is here) -> Minari
datasets of its episodes, of a mix with a random policy and of its replay buffer -> a DT trained
on one -> a report. (`make test` distributes whole modules to workers, so the chain is built once.)
"""

from __future__ import annotations

import json

import gymnasium as gym
import minari
import numpy as np
import pytest
from minari.data_collector import EpisodeBuffer

from tests.conftest import (
    all_runs,
    compose_cfg,
    metric_steps,
    new_store,
    one_line_error,
    pendulum_report,
    run_cli,
)
from walkers.data import datasets
from walkers.data.datasets import OfflineData
from walkers.data.replay import replay_episodes
from walkers.errors import ConfigError
from walkers.train import train
from walkers.training.bookkeeping import offline_references
from walkers.training.dataset_recording import collect, play
from walkers.training.envs import make_env
from walkers.training.run import agent_from_checkpoint, read_checkpoint
from walkers.training.settings import validate

pytestmark = pytest.mark.slow  # `make test-slow`, beside `make test` in CI

EXPERT = "walkers/pendulum/td3-v0"  # greedy TD3 episodes: returns from about -1500 to 0
MIXED = "walkers/pendulum/mixed-v0"  # 3 random-policy episodes, then 3 noisy TD3 ones
EPISODES = 40
#: A small DT that learns Pendulum in a minute (the reference sizes are for MuJoCo walkers).
SMALL_DT = [
    "algo.embed_dim=64",
    "algo.n_layers=2",
    "algo.context_length=10",
    "algo.dropout=0.0",
    "algo.lr=1e-3",
    "algo.warmup_steps=100",
]
DT_STEPS = 1500
HIGH, LOW = -150, -1200  # target returns: a swing-up policy's, a random policy's

PENDULUM_TD3_STEPS = 8000


@pytest.fixture(scope="module")
def pendulum_td3(tmp_path_factory, _empty_store_file) -> dict:
    """TD3 trained briefly on Pendulum-v1 (64-64 nets, 8k steps, replay buffer saved) in a store."""
    store = new_store(tmp_path_factory.mktemp("pendulum_td3"), _empty_store_file)
    train(
        compose_cfg(
            [
                "algo=td3",
                "env=pendulum",
                "seed=0",
                f"total_steps={PENDULUM_TD3_STEPS}",
                "eval_every=2000",
                "eval_episodes=5",
                "checkpoint_every=4000",
                "algo.hidden_sizes=[64,64]",
                "save_buffer=true",
                "progress=false",
                *store["overrides"],
            ]
        )
    )
    (run,) = all_runs(store["client"])
    return {**store, "run": run}


def test_td3_learns_pendulum(pendulum_td3):
    """A random policy scores about -1200 on Pendulum-v1; a swing-up policy about -150."""
    client, run_id = pendulum_td3["client"], pendulum_td3["run"].info.run_id
    history = [m.value for m in client.get_metric_history(run_id, "eval/return_mean")]
    print(history)
    assert history[0] < -900, history  # it started from a poor policy ...
    assert max(history) >= -300, history  # ... and learned to swing up


@pytest.fixture(scope="module")
def offline(pendulum_td3):
    """Datasets recorded from the TD3 run and a DT trained on one, in the TD3 run's store.

    MINARI_DATASETS_PATH points into the store's folder while the module's tests run.
    """
    store, td3_run = pendulum_td3, pendulum_td3["run"]
    minari_root = store["path"] / "minari"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(minari_root))
        collected = run_cli(
            [
                "run_id=latest",  # the TD3 run: the only training run in the store yet
                f"episodes={EPISODES}",
                f"dataset={EXPERT.removesuffix('-v0')}",
                *store["overrides"],
            ],
            cwd=store["path"],
            module="walkers.collect",
            env_overrides={"MINARI_DATASETS_PATH": str(minari_root)},
        )
        assert collected.returncode == 0, collected.stderr[-3000:]
        mixed = collect(
            compose_cfg(
                [
                    f"run_id=[random,{td3_run.info.run_id}]",
                    "env=pendulum",
                    "episodes=3",
                    "exploration_noise=0.1",
                    f"dataset={MIXED}",
                    "log_to_mlflow=false",
                    *store["overrides"],
                ],
                config_name="collect",
            )
        )
        train(
            compose_cfg(
                [
                    "algo=dt",
                    "env=pendulum",
                    f"dataset={EXPERT}",
                    f"total_steps={DT_STEPS}",
                    "eval_every=750",
                    "checkpoint_every=750",
                    "log_every=100",
                    "eval_episodes=4",
                    f"algo.target_returns=[{HIGH},{LOW}]",
                    "progress=false",
                    *SMALL_DT,
                    *store["overrides"],
                ]
            )
        )
        yield {
            **store,
            "td3_run": td3_run,
            "collect_stdout": collected.stdout,
            "mixed": mixed,
            "minari_root": minari_root,
        }


def _run(store, algo: str):
    (run,) = [r for r in all_runs(store["client"]) if r.data.tags.get("algo") == algo]
    return run


def _last(store, run, key: str) -> float:
    return store["client"].get_metric_history(run.info.run_id, key)[-1].value


def test_collected_episodes_load_back_the_same(offline):
    """Mixed policies in one dataset; replaying them from the same seeds gives the same data."""
    data = datasets.load_local(MIXED)
    assert data.env_id == "Pendulum-v1" and len(data.episodes) == 6
    assert offline["mixed"]["episodes"] == 6 and len(offline["mixed"]["sources"]) == 2
    shapes = {(e.observations.shape, e.actions.shape) for e in data.episodes}
    assert shapes == {((201, 3), (200, 1))}
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": 200}, shaping=False)
    rng = np.random.default_rng(0)  # collect's default seed
    again = play(None, env, 3, seed=0, noise=0.0, rng=rng)  # policy 0: random, seeds 0..2
    state = read_checkpoint(
        offline["client"].download_artifacts(
            offline["td3_run"].info.run_id, "checkpoints/best.pt", str(offline["path"] / "dl")
        )
    )
    _, td3 = agent_from_checkpoint(state, env, "cpu")
    again += play(td3, env, 3, seed=3, noise=0.1, rng=rng)  # policy 1: noisy TD3, seeds 3..5
    env.close()
    for stored, replayed in zip(data.episodes, again, strict=True):
        np.testing.assert_array_equal(stored.observations, replayed.observations)
        np.testing.assert_array_equal(stored.actions, replayed.actions)
        np.testing.assert_allclose(stored.rewards, replayed.rewards)
        assert stored.truncations[-1] and not stored.terminations.any()


def test_dataset_stats_are_printed_logged_and_stored(offline):
    data = datasets.load_local(EXPERT)
    returns = data.returns
    client = offline["client"]
    (run,) = [r for r in all_runs(client) if r.data.tags.get("walkers.kind") == "dataset"]
    assert run.info.status == "FINISHED" and run.data.tags["dataset"] == EXPERT
    assert run.data.metrics["dataset/episodes"] == EPISODES
    assert run.data.metrics["dataset/return_mean"] == pytest.approx(returns.mean())
    logged = [m.value for m in client.get_metric_history(run.info.run_id, "dataset/episode_return")]
    np.testing.assert_allclose(sorted(logged), sorted(returns))
    # the normalization references: the behaviour policy's mean return, a random policy's
    assert data.behaviour_return == pytest.approx(returns.mean())
    assert data.random_return < -900 < data.behaviour_return
    assert f"dataset {EXPERT}: {EPISODES} episodes" in offline["collect_stdout"]
    assert run.data.params["run_id"] == str([offline["td3_run"].info.run_id])  # run_id=latest
    assert (offline["minari_root"] / EXPERT / "data").is_dir()
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"stats.json", "returns.png"} <= artifacts


def test_replay_dataset_holds_every_training_episode(offline):
    """The run's replay buffer cut into episodes: the same returns as its training episodes."""
    run_id = offline["td3_run"].info.run_id
    path = offline["client"].download_artifacts(
        run_id, "checkpoints/last.pt", str(offline["path"] / "dl-last")
    )
    episodes = replay_episodes(read_checkpoint(path)["agent"]["buffer"])
    trained = [
        m.value for m in offline["client"].get_metric_history(run_id, "train/episode_return")
    ]
    assert len(episodes) == PENDULUM_TD3_STEPS // 200 == len(trained)
    np.testing.assert_allclose([e.episode_return for e in episodes], trained, rtol=1e-5)
    assert all(e.truncations[-1] and not e.terminations.any() for e in episodes)


def test_dt_clearly_beats_a_random_policy(offline):
    run = _run(offline, "dt")
    data = datasets.load_local(EXPERT)
    final = _last(offline, run, "eval/return_mean")  # conditioned on HIGH
    print("DT", final, "random policy", data.random_return, "dataset", data.returns.mean())
    assert final > data.random_return + 500
    score = _last(offline, run, "eval/normalized_score")  # Pendulum has no expert in conf/env:
    low, high = data.random_return, data.behaviour_return  # the dataset's own references
    assert score == pytest.approx(100 * (final - low) / (high - low))
    assert run.data.params["normalized_score.references"] == "dataset"
    assert score > 50  # at least half way from a random policy to the dataset's policy


def test_each_target_return_is_evaluated_and_steers_the_policy(offline):
    """Every target in algo.target_returns gets its own evaluation, and the return-to-go reaches
    the actions. (Whether a higher target earns more depends on the data: in greedy episodes of
    one policy the return follows the start state, not the behaviour, so there is nothing to
    condition on; README, Offline.)"""
    run = _run(offline, "dt")
    for target in (HIGH, LOW):
        assert np.isfinite(_last(offline, run, f"eval/target_{target}/return_mean"))
    state = read_checkpoint(
        offline["client"].download_artifacts(
            run.info.run_id, "checkpoints/last.pt", str(offline["path"] / "dt_last")
        )
    )
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": 200}, shaping=False)
    _, dt = agent_from_checkpoint(state, env, "cpu")
    actions = {}
    for target in (HIGH, LOW):
        dt.target_return = target
        dt.begin_episode()
        obs, _ = env.reset(seed=0)
        actions[target] = [dt.act(obs)]
        for _ in range(5):  # the same states, so only the return-to-go differs
            dt.record_reward(-1.0)
            actions[target].append(dt.act(obs))
    env.close()
    assert not np.allclose(actions[HIGH], actions[LOW])


def test_report_puts_dt_beside_td3(offline, tmp_path):
    comparison, out, _ = pendulum_report(offline["overrides"], ["td3", "dt"], tmp_path)
    dt = next(r for r in comparison.algos if r.algo == "dt")
    assert dt.x_axis == "gradient_steps" and dt.dataset == EXPERT
    assert comparison.budgets == {"env_steps": PENDULUM_TD3_STEPS, "gradient_steps": DT_STEPS}
    assert [p.quantity for p in comparison.pairs] == ["score"]  # no AUC across x-axes
    report = (out / "report.md").read_text()
    assert f"dt (offline, {EXPERT})" in report and f"{DT_STEPS:,} gradient steps" in report
    summary = json.loads((out / "summary.json").read_text())
    assert summary["algos"]["dt"]["dataset"] == EXPERT
    normalized = _last(offline, _run(offline, "dt"), "final/normalized_score")
    assert summary["algos"]["dt"]["normalized_score_mean"] == pytest.approx(normalized)
    dt_summary = summary["algos"]["dt"]
    assert dt_summary["references"]["source"] == "dataset"
    low, high = dt_summary["references"]["random"], dt_summary["references"]["expert"]
    iqm = dt_summary["iqm"]
    assert dt_summary["normalized_iqm"]["point"] == pytest.approx(100 * (iqm - low) / (high - low))
    assert dt_summary["behaviour_score"] == pytest.approx(100)  # the behaviour is the reference
    assert f"dt (offline, {EXPERT}): normalized score" in report
    assert "the data's behaviour policy: return" in report
    # each target return the DT was asked for, highest first, with the seed's final return there
    per_target = dt_summary["per_target"]
    assert list(per_target) == [f"{HIGH:g}", f"{LOW:g}"]
    for target in (HIGH, LOW):
        final = _last(offline, _run(offline, "dt"), f"eval/target_{target}/return_mean")
        assert per_target[f"{target:g}"]["iqm"] == pytest.approx(final)  # one seed: its own
        score = per_target[f"{target:g}"]["normalized_iqm"][0]
        assert score == pytest.approx(100 * (final - low) / (high - low))
    assert f"dt (offline, {EXPERT}) by target return" in report
    assert summary["algos"]["td3"]["per_target"] == {}  # an online arm has none
    assert (out / "learning_curves.png").stat().st_size > 0


def test_env_references_make_scores_on_different_datasets_compare():
    """conf/env's scores.random and scores.expert, where both are set, outrank a dataset's own."""
    data = OfflineData("d", "Walker2d-v5", [], random_return=-5.0, behaviour_return=900.0)
    walker = compose_cfg(["env=walker2d", "env.scores.expert=4000", "env.scores.random=0"]).env
    references = offline_references(walker, data)
    assert (references.source, references.normalized(0), references.normalized(4000)) == (
        "env",
        0,
        100,
    )
    pendulum = compose_cfg(["env=pendulum"]).env  # no expert: the dataset's random and behaviour
    own = offline_references(pendulum, data)
    assert own.source == "dataset" and own.normalized(900.0) == 100 and own.normalized(-5.0) == 0
    unknown = OfflineData("d", None, [], None, None)
    assert offline_references(pendulum, unknown).normalized(1) is None


def test_replay_steps_keep_what_the_run_saw_first(offline):
    """replay_steps=N: the episodes of the run's first N env steps (a medium-replay dataset)."""
    run_id = offline["td3_run"].info.run_id
    overrides = [f"run_id={run_id}", "replay=true", "log_to_mlflow=false", *offline["overrides"]]
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(offline["minari_root"]))
        stats = collect(
            compose_cfg(
                [*overrides, "replay_steps=1000", "dataset=walkers/pendulum/first-1000"],
                config_name="collect",
            )
        )
        trained = [
            m.value for m in offline["client"].get_metric_history(run_id, "train/episode_return")
        ]
        assert stats["episodes"] == 5 and stats["steps"] == 1000  # 200-step episodes
        data = datasets.load_local("walkers/pendulum/first-1000")
        np.testing.assert_allclose(data.returns, trained[:5], rtol=1e-5)
        for bad, message in [
            ("replay_steps=9000", "replay_steps=9000 is not allowed: must be between 1 and"),
            ("replay_steps=0", "replay_steps=0 is not allowed: an integer > 0, with replay=true"),
        ]:
            with pytest.raises(ConfigError, match=message):
                collect(compose_cfg([*overrides, bad, "dataset=x"], config_name="collect"))
        assert not datasets.exists("x")


def test_dt_run_counts_gradient_steps_and_resumes(offline):
    run = _run(offline, "dt")
    assert run.info.status == "FINISHED"
    assert run.data.tags["walkers.x_axis"] == "gradient_steps"
    assert run.data.tags["dataset"] == EXPERT
    assert run.data.params["dataset_stats.episodes"] == str(EPISODES)
    client = offline["client"]
    assert metric_steps(client, run.info.run_id, "eval/return_mean") == [750, 1500]
    assert "perf/gradient_steps_per_s" in run.data.metrics
    assert {a.path for a in client.list_artifacts(run.info.run_id, "checkpoints")} == {
        "checkpoints/best.pt",
        "checkpoints/last.pt",
    }
    # 100 more gradient steps: the same run continues, no step logged twice.
    more = DT_STEPS + 100
    train(
        compose_cfg([f"resume={run.info.run_id}", f"total_steps={more}", *offline["overrides"]]),
        overrides=[f"total_steps={more}"],
    )
    steps = metric_steps(client, run.info.run_id, "loss/action")
    assert steps == sorted(set(steps)) and steps[-1] == more
    assert client.get_run(run.info.run_id).info.status == "FINISHED"


def test_offline_bad_input(offline):
    with pytest.raises(ConfigError, match=r"dataset=None is not allowed: algo=dt"):
        validate(compose_cfg(["algo=dt", "env=pendulum"]))
    with pytest.raises(ConfigError, match=r"dataset='x' is not allowed with algo=td3"):
        validate(compose_cfg(["algo=td3", "dataset=x"]))
    with pytest.raises(ConfigError, match=rf"dataset='nope' is not a local.*{EXPERT}"):
        train(compose_cfg(["algo=dt", "env=pendulum", "dataset=nope", *offline["overrides"]]))
    with pytest.raises(ConfigError, match=r"recorded on Pendulum-v1, not on env.id='Hopper-v5'"):
        train(compose_cfg(["algo=dt", "env=hopper", f"dataset={EXPERT}", *offline["overrides"]]))
    before = len(all_runs(offline["client"]))
    result = run_cli(
        [f"run_id={offline['td3_run'].info.run_id}", f"dataset={EXPERT}", *offline["overrides"]],
        cwd=offline["path"],
        module="walkers.collect",
        env_overrides={"MINARI_DATASETS_PATH": str(offline["minari_root"])},
    )
    assert "already exists" in one_line_error(result) and "overwrite=true" in result.stderr
    assert len(all_runs(offline["client"])) == before  # no run created, nothing overwritten
    assert minari.load_dataset(EXPERT).total_episodes == EPISODES


@pytest.mark.filterwarnings("ignore::UserWarning")  # Minari asks for author, description ...
def test_a_dataset_made_elsewhere_trains_too(offline):
    """Any local Minari dataset of the env works, e.g. a downloaded one: no walkers metadata,
    no reference returns (so no normalized score), observations in float64."""
    env = gym.make("Pendulum-v1")
    rng = np.random.default_rng(1)
    buffers = []
    for i in range(3):
        observations = [env.reset(seed=100 + i)[0]]
        actions = rng.uniform(-2, 2, (200, 1)).astype(np.float32)
        rewards = []
        for action in actions:
            obs, reward, *_ = env.step(action)
            observations.append(obs)
            rewards.append(reward)
        buffers.append(
            EpisodeBuffer(
                id=i,
                observations=np.asarray(observations, dtype=np.float64),
                actions=actions,
                rewards=np.asarray(rewards),
                terminations=np.zeros(200, bool),
                truncations=np.r_[np.zeros(199, bool), True],
            )
        )
    minari.create_dataset_from_buffers("elsewhere/pendulum/random-v1", buffers, env=env)
    train(
        compose_cfg(
            [
                "algo=dt",
                "env=pendulum",
                "dataset=elsewhere/pendulum/random-v1",
                "total_steps=20",
                "eval_every=20",
                "checkpoint_every=20",
                "log_every=10",
                "eval_episodes=1",
                "progress=false",
                *SMALL_DT,
                *offline["overrides"],
            ]
        )
    )
    (run,) = [
        r
        for r in all_runs(offline["client"])
        if r.data.tags.get("dataset") == "elsewhere/pendulum/random-v1"
    ]
    assert run.info.status == "FINISHED" and "eval/return_mean" in run.data.metrics
    assert "eval/normalized_score" not in run.data.metrics  # no reference returns to use
    best = max(b.rewards.sum() for b in buffers)  # target_returns: null -> the best episode
    assert run.data.params["algo.target_returns"] == "None"
    assert f"eval/target_{best:g}/return_mean" in run.data.metrics
