"""Every declared online algorithm through the entrypoint (tiny runs on Pendulum), the walking
robots end to end, and what is particular to REINFORCE and DDPG."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import DESIGN_METRICS, ONLINE, TINY, all_runs, compose_cfg, tiny
from tests.fingerprints import CASES
from walkers.agents.base import Transition
from walkers.agents.ddpg import DDPG
from walkers.agents.factory import defaults_for
from walkers.agents.reinforce import Reinforce, returns_to_go
from walkers.train import train
from walkers.training.envs import make_env

OFF_POLICY_TINY = tiny("ddpg")
REINFORCE_TINY = tiny("reinforce")


def test_the_online_algorithms_are_the_declared_ones():
    assert {"reinforce", "ppo", "ddpg", "td3", "sac", "crossq"} <= set(ONLINE)
    assert "dt" not in ONLINE


#: What an algorithm logs of its update beside the design's metrics, where it says more.
OWN_METRICS = {
    "ppo": {"loss/policy", "loss/value", "train/approx_kl", "train/lr"},
    "sac": {"loss/critic", "loss/alpha", "train/alpha"},
    "crossq": {"loss/critic", "loss/alpha", "train/alpha"},
}


@pytest.mark.parametrize("algo", ONLINE)
def test_every_algorithm_trains_through_the_entrypoint_and_logs_the_design_metrics(store, algo):
    """Each declared online algorithm, a tiny run on Pendulum: FINISHED, tagged, every design
    metric and its own (a new algorithm is covered with no edit: ONLINE is the declarations')."""
    train(compose_cfg([f"algo={algo}", "env=pendulum", *TINY, *tiny(algo), *store["overrides"]]))
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED" and run.data.tags["algo"] == algo
    assert DESIGN_METRICS | OWN_METRICS.get(algo, set()) | {"train/episode_return"} <= set(
        run.data.metrics
    )
    assert run.data.metrics.get("health/skipped_updates", 0) == 0


@pytest.mark.parametrize("env", ["bipedal_walker", "walker2d"])
def test_the_walking_robots_train_end_to_end(store, env):
    """Box2D's and MuJoCo's walkers through the whole path (one off-policy learner: the envs'
    side, their spaces, episodes and recorded returns, is what differs from Pendulum)."""
    train(compose_cfg(["algo=td3", f"env={env}", *TINY, *tiny("td3"), *store["overrides"]]))
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED" and DESIGN_METRICS <= set(run.data.metrics)
    assert "train/episode_return" in run.data.metrics  # short walker episodes: some ended


def test_ddpg_tutorial_variant_layernorm_critic_and_ou_noise(store):
    cfg = compose_cfg(
        [
            "algo=ddpg",
            "env=pendulum",
            "algo.critic_architecture=layernorm_branch",
            "algo.critic_hidden_sizes=[64,32,16]",
            "algo.noise_type=ou",
            *TINY,
            *OFF_POLICY_TINY,
            *store["overrides"],
        ]
    )
    train(cfg)
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED" and run.data.params["algo.noise_type"] == "ou"


def test_ddpg_is_the_shared_core_with_one_critic():
    agent = DDPG(3, [-2.0], [2.0], **defaults_for(DDPG, learning_starts=0, batch_size=8))
    q = agent.critic(torch.zeros(5, 3), torch.zeros(5, 1))
    assert q.shape == (1, 5)  # one critic (TD3 has two)
    assert (agent.policy_delay, agent.policy_noise) == (1, 0.0)


def test_returns_to_go():
    np.testing.assert_allclose(returns_to_go(np.array([1.0, 1.0, 1.0]), 0.5), [1.75, 1.5, 1.0])


def test_reinforce_nan_guard_skips_the_update_and_training_continues():
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": 20})
    agent = Reinforce(3, [-2.0], [2.0], seed=0, **defaults_for(Reinforce, episodes_per_update=1))
    obs, _ = env.reset(seed=0)

    def play_episode(reward_override=None):
        nonlocal obs
        for t in range(20):
            action = agent.act(obs, explore=True)
            next_obs, reward, term, trunc, _ = env.step(action)
            reward = reward if reward_override is None else reward_override
            agent.observe(Transition(obs, action, reward, next_obs, term, t == 19))
            obs = next_obs
        obs, _ = env.reset()
        return agent.update()

    before = {k: v.clone() for k, v in agent.policy.state_dict().items()}
    metrics = play_episode(reward_override=float("nan"))  # a non-finite loss
    assert metrics["health/skipped_updates"].item() == 1
    for k, v in agent.policy.state_dict().items():
        assert torch.equal(v, before[k]) and torch.isfinite(v).all()
    metrics = play_episode()  # and the next update goes through
    assert metrics["health/skipped_updates"].item() == 1
    assert any(not torch.equal(v, before[k]) for k, v in agent.policy.state_dict().items())


def test_fall_penalty_shapes_learning_but_not_reported_returns():
    env = make_env({"id": "BipedalWalker-v3", "max_episode_steps": 1600, "fall_penalty": -1.0})
    env.reset(seed=0)
    rewards, info, done = [], {}, False
    while not done:  # falling forward: legs limp, hull hits the ground
        _, reward, term, trunc, info = env.step(np.array([1.0, -1.0, 1.0, -1.0], dtype=np.float32))
        rewards.append(reward)
        done = term or trunc
    assert term and min(rewards) == -1.0  # the -100 fall became -1 for the learner
    assert info["episode"]["r"] < sum(rewards) - 90  # the recorded return is the env's own


def test_discrete_action_space_is_rejected_before_training(store):
    from walkers.errors import ConfigError

    with pytest.raises(ConfigError, match="Discrete"):
        train(compose_cfg(["env=pendulum", "env.id=CartPole-v1", *TINY, *store["overrides"]]))
    assert all_runs(store["client"]) == []


def test_any_continuous_gymnasium_id_works_by_override(store):
    train(
        compose_cfg(
            [
                "algo=reinforce",
                "env=pendulum",
                "env.id=MountainCarContinuous-v0",
                "env.max_episode_steps=100",
                *TINY,
                *REINFORCE_TINY,
                *store["overrides"],
            ]
        )
    )
    (run,) = all_runs(store["client"])
    assert run.data.tags["env"] == "MountainCarContinuous-v0" and run.info.status == "FINISHED"


def test_every_online_algorithm_has_a_seeded_fingerprint():
    """tests/fingerprints.py proves a restructuring changed no behaviour: for every algorithm."""
    fingerprinted = {
        o.removeprefix("algo=") for case in CASES.values() for o in case if o.startswith("algo=")
    }
    assert set(ONLINE) <= fingerprinted
