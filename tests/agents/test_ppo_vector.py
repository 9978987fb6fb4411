"""PPO on several envs stepped together (``algo.num_envs``): each env's stream keeps its own
episodes and GAE, the reward scaler shares its statistics and keeps a return per env, what is
reported is the envs' own returns, a run resumes with every env's RNG, and bad sizes are refused
in one line with nothing created."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import PPO_TINY, all_runs, compose_cfg, new_store, one_line_error, run_cli
from walkers.agents.base import Transition
from walkers.agents.common.normalization import RewardScaler
from walkers.agents.factory import defaults_for
from walkers.agents.ppo import PPO
from walkers.errors import ConfigError
from walkers.train import train
from walkers.training.run import read_checkpoint
from walkers.training.settings import validate

VECTOR = ["algo=ppo", "env=pendulum", "algo.num_envs=4", *PPO_TINY]
VECTOR += ["eval_episodes=1", "log_every=100"]
VECTOR += ["progress=false"]


def _feed(agent: PPO, steps: int, ends: dict[tuple[int, int], str], seed: int = 0) -> None:
    """``steps`` batch steps of made-up transitions; ``ends[(step, env)]``: terminated or
    truncated there."""
    rng = np.random.default_rng(seed)
    for step in range(steps):
        obs = rng.normal(size=(agent.num_envs, 3)).astype(np.float32)
        actions = agent.act(obs, explore=True)
        agent.observe_batch(
            [
                Transition(
                    obs[i],
                    actions[i],
                    float(rng.normal()),
                    obs[i] + 1.0,
                    ends.get((step, i)) == "terminated",
                    ends.get((step, i)) == "truncated",
                )  # fmt: skip
                for i in range(agent.num_envs)
            ]
        )


def test_each_envs_stream_keeps_its_own_episodes_and_gae():
    """The rollout of two envs is, env by env, what the same agent computes for each stream
    alone: no advantage leaks across envs, each stream's last step bootstraps."""
    hp = defaults_for(PPO, n_steps=12, num_envs=2, n_minibatches=2, normalize_reward=False)
    agent = PPO(3, [-1.0], [1.0], seed=0, **hp)
    _feed(agent, 6, {(1, 0): "terminated", (3, 1): "truncated"})
    streams = [rollout.take() for rollout in agent.rollouts]
    assert [s["episode_end"].tolist() for s in streams] == [
        [False, True, False, False, False, False],
        [False, False, False, True, False, False],
    ]
    together = agent._prepare_batch(streams)
    alone = [agent._prepare_batch([stream]) for stream in streams]
    for key in ("advantages", "returns", "old_values", "old_log_prob"):
        torch.testing.assert_close(together[key], torch.cat([a[key] for a in alone]))


def test_one_env_scaled_as_a_batch_is_the_single_env_scaler():
    single, batch = RewardScaler(0.99, True), RewardScaler(0.99, True, num_envs=1)
    rewards, ends = [1.0, -2.0, 0.5, 3.0], [False, True, False, False]
    scaled = [single(r, e) for r, e in zip(rewards, ends, strict=True)]
    batched = [batch.scale_batch([r], [e])[0] for r, e in zip(rewards, ends, strict=True)]
    assert batched == scaled


def test_several_envs_share_the_statistics_and_keep_a_return_each():
    scaler = RewardScaler(0.5, True, num_envs=2)
    scaler.scale_batch([1.0, 2.0], [True, False])
    assert scaler.discounted_return.tolist() == [0.0, 2.0]  # env 0's episode ended
    assert scaler.rms.count == pytest.approx(2 + 1e-4)  # both returns, one update
    scaler.scale_batch([1.0, 1.0], [False, False])
    assert scaler.discounted_return.tolist() == [1.0, 2.0]
    state = scaler.state_dict()
    again = RewardScaler(0.5, True, num_envs=2)
    again.load_state_dict(state)
    assert again.discounted_return.tolist() == [1.0, 2.0]


@pytest.fixture(scope="module")
def vector_run(tmp_path_factory, _empty_store_file):
    """Four Pendulum envs (episodes of 200 steps) for 1,600 steps: 400 each, two episodes
    each; the rewards each env hands the agent, summed per episode."""
    store = new_store(tmp_path_factory.mktemp("vector"), _empty_store_file)
    returns, current = [], np.zeros(4)

    def observe_batch(self, transitions):
        for i, t in enumerate(transitions):
            current[i] += t.reward
            if t.episode_over:
                returns.append(current[i])
                current[i] = 0.0
        original(self, transitions)

    original = PPO.observe_batch
    args = [*VECTOR, "total_steps=1600", "eval_every=800", "checkpoint_every=800"]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(PPO, "observe_batch", observe_batch)
        train(compose_cfg([*args, *store["overrides"]]))
    (run,) = all_runs(store["client"])
    return {**store, "run": run, "env_returns": returns}


def test_a_vectorized_run_reports_every_envs_episodes_with_their_own_returns(vector_run):
    client, run = vector_run["client"], vector_run["run"]
    assert run.info.status == "FINISHED"
    logged = client.get_metric_history(run.info.run_id, "train/episode_return")
    assert len(logged) == 8 == len(vector_run["env_returns"])  # 4 envs x 2 episodes
    assert sorted(m.value for m in logged) == pytest.approx(sorted(vector_run["env_returns"]))
    # the four envs end their episodes in the same step (200 each): steps 797-800, 1597-1600
    assert [m.step for m in logged] == [797, 798, 799, 800, 1597, 1598, 1599, 1600]
    path = client.download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(vector_run["path"] / "final")
    )
    state = read_checkpoint(path)
    agent = state["agent"]
    assert (agent["steps"], agent["num_updates"], agent["rollout_steps"]) == (1600, 12, 64)
    assert len(state["env_rng"]["envs"]) == 4  # every env's RNG, for a resume


def test_a_vectorized_run_resumes_with_every_envs_rng_and_a_rerun_trains_nothing(vector_run):
    store, run_id = vector_run, vector_run["run"].info.run_id
    resumed = run_cli([f"resume={run_id}", "total_steps=2400", *store["overrides"]], store["path"])
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    episodes = store["client"].get_metric_history(run_id, "train/episode_return")
    assert len(episodes) == 12  # the resumed envs start new episodes: 4 more by step 2400
    assert max(m.step for m in episodes) == 2400


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["algo.num_envs=3"], "algo.num_envs=3 is not allowed: must divide algo.n_steps (128)"),
        (
            ["total_steps=1002"],
            "total_steps=1002 is not allowed: must be a multiple of algo.num_envs (4)",
        ),
        (
            ["checkpoint_every=502"],
            "checkpoint_every=502 is not allowed: must be a multiple of algo.num_envs (4)",
        ),
        (["impl=sb3"], "algo.num_envs=4 cannot be expressed with impl=sb3 (ppo): must be 1"),
    ],
)
def test_bad_sizes_are_refused_in_one_line(overrides, message):
    with pytest.raises(ConfigError) as refused:
        validate(compose_cfg([*VECTOR, "total_steps=1000", "eval_every=500", *overrides]))
    assert message in str(refused.value)


def test_a_bad_num_envs_through_the_cli_exits_2_and_creates_nothing(store):
    result = run_cli([*VECTOR, "algo.num_envs=5", *store["overrides"]], store["path"])
    assert result.returncode == 2
    assert "algo.num_envs=5 is not allowed: must divide algo.n_steps (128)" in one_line_error(
        result
    )
    assert all_runs(store["client"]) == []


def test_a_several_envs_config_has_its_own_update_fingerprint(monkeypatch, tmp_path):
    """What an export records for a run of it (walkers.analysis.fingerprint): driven through a
    batch of envs, and not the single env's."""
    from walkers.analysis.fingerprint import update_fingerprint

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    several = update_fingerprint(compose_cfg([*VECTOR, "algo.num_envs=2"]).algo)
    single = update_fingerprint(compose_cfg([*VECTOR, "algo.num_envs=1"]).algo)
    assert len(several) > 10 and several != single


def test_one_step_at_a_time_is_refused_with_several_envs():
    hp = defaults_for(PPO, n_steps=8, n_minibatches=2, num_envs=2)
    agent = PPO(3, [-1.0], [1.0], seed=0, **hp)
    agent.act(np.zeros((2, 3), np.float32), explore=True)
    with pytest.raises(ValueError, match="num_envs=2 observes a batch"):
        agent.observe(Transition(np.zeros(3), np.zeros(1), 0.0, np.zeros(3), False, False))
