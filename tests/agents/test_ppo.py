"""PPO: the math pinned by hand, normalization that never changes what is reported, checkpoints and
resume with the normalizer's statistics, evaluate/collect on a PPO policy, and learning.

(Tiny runs on pendulum, bipedal_walker and walker2d are in test_algorithms.py's table.)
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from tests.conftest import PPO_TINY, TINY, all_runs, compose_cfg, new_store, run_cli
from walkers.agents.base import Transition
from walkers.agents.factory import defaults_for
from walkers.agents.ppo import PPO, ROLLOUT_RESTART_TAG, clipped_surrogate, value_loss
from walkers.data.rollouts import Rollout, gae
from walkers.errors import ConfigError
from walkers.train import train
from walkers.training.envs import make_env
from walkers.training.run import read_checkpoint
from walkers.training.settings import validate

SMALL = PPO_TINY

# --- GAE by hand ------------------------------------------------------------------------------
# Five steps, gamma = lambda = 0.5 (gamma * lambda = 0.25), V(s) = s:
#   t  s    r  s'   ends by          V(s'_t) used
#   0  0.5  1  1    -                V(s_1) = 1
#   1  1    0  7    terminated       none (terminal: not bootstrapped)
#   2  0    2  1    -                V(s_3) = 1
#   3  1    1  4    truncated        V(s'_3) = 4 (the time limit's next state, bootstrapped)
#   4  2    0  2    (rollout end)    V(s'_4) = 2 (the unfinished episode, bootstrapped)
# delta_t = r_t + gamma V(s'_t) - V(s_t); A_t = delta_t + 0.25 A_{t+1} inside an episode:
#   A_4 = 0 + 1 - 2 = -1
#   A_3 = 1 + 2 - 1 = 2                   (the trace stops at the truncation)
#   A_2 = (2 + 0.5 - 0) + 0.25 * 2 = 3
#   A_1 = 0 + 0 - 1 = -1                  (terminal)
#   A_0 = (1 + 0.5 - 0.5) + 0.25 * -1 = 0.75
STATES = [0.5, 1.0, 0.0, 1.0, 2.0]
REWARDS = [1.0, 0.0, 2.0, 1.0, 0.0]
NEXT_STATES = [1.0, 7.0, 1.0, 4.0, 2.0]
TERMINATED = [False, True, False, False, False]
TRUNCATED = [False, False, False, True, False]
ADVANTAGES = [0.75, -1.0, 3.0, 2.0, -1.0]


def test_gae_matches_the_hand_computed_trajectory_with_a_terminal_and_a_truncation():
    ends = np.logical_or(TERMINATED, TRUNCATED)
    next_values = [1.0, 99.0, 1.0, 4.0, 2.0]  # 99: after the terminal, never read
    advantages, returns = gae(REWARDS, STATES, next_values, TERMINATED, ends, 0.5, 0.5)
    np.testing.assert_allclose(advantages, ADVANTAGES)
    np.testing.assert_allclose(returns, np.add(ADVANTAGES, STATES))  # the value targets
    as_terminal, _ = gae(REWARDS, STATES, next_values, ends, ends, 0.5, 0.5)
    assert as_terminal[3] == 0.0  # a truncation taken for a terminal loses the bootstrap (2.0)


def test_the_agent_bootstraps_a_truncation_from_its_own_next_state():
    """The same trajectory through the agent: which V(s') it bootstraps from is its own choice."""
    agent = PPO(1, [-1.0], [1.0], **defaults_for(PPO, n_steps=5, n_minibatches=1, gamma=0.5,
                gae_lambda=0.5, normalize_obs=False, normalize_reward=False))  # fmt: skip
    agent.value = nn.Linear(1, 1)
    with torch.no_grad():  # V(s) = s
        agent.value.weight.fill_(1.0)
        agent.value.bias.zero_()
    for s, r, s2, term, trunc in zip(
        STATES, REWARDS, NEXT_STATES, TERMINATED, TRUNCATED, strict=True
    ):
        action = agent.act(np.array([s], np.float32), explore=True)
        agent.observe(Transition(np.array([s]), action, r, np.array([s2]), term, trunc))
    batch = agent._prepare_batch([agent.rollouts[0].take()])
    np.testing.assert_allclose(batch["advantages"].numpy(), ADVANTAGES, rtol=1e-6)


# --- the clipped objective --------------------------------------------------------------------
@pytest.mark.parametrize(
    "advantage,ratio,loss,grad",
    [
        # A > 0: clipping binds above 1 + eps (no gain from raising pi further)
        (2.0, 0.5, -1.0, -2.0),
        (2.0, 0.9, -1.8, -2.0),
        (2.0, 1.1, -2.2, -2.0),
        (2.0, 1.5, -2.4, 0.0),  # -(1.2 * 2), gradient zero
        # A < 0: clipping binds below 1 - eps
        (-2.0, 0.5, 1.6, 0.0),  # -(0.8 * -2), gradient zero
        (-2.0, 0.9, 1.8, 2.0),
        (-2.0, 1.1, 2.2, 2.0),
        (-2.0, 1.5, 3.0, 2.0),  # the pessimistic (unclipped) term: still pushed down
    ],
)
def test_clipped_surrogate_value_and_gradient(advantage, ratio, loss, grad):
    r = torch.tensor([ratio], requires_grad=True)
    value = clipped_surrogate(r, torch.tensor([advantage]), clip_coef=0.2)
    value.sum().backward()
    assert value.item() == pytest.approx(loss)
    assert r.grad.item() == pytest.approx(grad)


def test_value_clipping_keeps_the_pessimistic_loss():
    returns, old = torch.tensor([1.0]), torch.tensor([0.0])
    new = torch.tensor([0.5], requires_grad=True)  # moved 0.5, more than the clip 0.2
    loss = value_loss(new, old, returns, clip_coef=0.2)
    assert loss.item() == pytest.approx(0.5 * 0.8**2)  # the clipped value 0.2 is further away
    loss.backward()
    assert new.grad.item() == 0.0
    assert value_loss(new, old, returns, None).item() == pytest.approx(0.5 * 0.5**2)


# --- the agent --------------------------------------------------------------------------------
def _play(agent: PPO, env, steps: int, obs=None, reward_override=None) -> list[dict]:
    """``steps`` training steps as the trainer takes them; the updates' metrics."""
    obs = env.reset(seed=0)[0] if obs is None else obs
    updates = []
    for _ in range(steps):
        action = agent.act(obs, explore=True)
        next_obs, reward, term, trunc, _ = env.step(action)
        reward = reward if reward_override is None else reward_override
        agent.observe(Transition(obs, action, float(reward), next_obs, term, trunc))
        if metrics := agent.update():
            updates.append(metrics)
        obs = next_obs if not (term or trunc) else env.reset()[0]
    return updates


def _pendulum():
    return make_env({"id": "Pendulum-v1", "max_episode_steps": 50})


def _small_agent(seed: int = 0, **kw) -> PPO:
    small = defaults_for(PPO, n_steps=64, n_minibatches=4, n_epochs=2, **kw)
    return PPO(3, [-2.0], [2.0], seed=seed, **small)


def test_same_seed_same_agent_another_seed_another():
    agents = [_small_agent(seed) for seed in (0, 0, 1)]
    for agent in agents:
        _play(agent, _pendulum(), 200)
    same = [torch.equal(a, b) for a, b in zip(agents[0].params, agents[1].params, strict=True)]
    other = [torch.equal(a, b) for a, b in zip(agents[0].params, agents[2].params, strict=True)]
    assert all(same) and not any(other)


def test_normalizer_statistics_update_only_while_exploring():
    agent = _small_agent()
    env = _pendulum()
    _play(agent, env, 30)
    rms = agent.obs_normalizer.rms
    count, mean = rms.count, rms.mean.copy()
    obs = env.reset(seed=5)[0]
    first = agent.act(obs, explore=False)
    for _ in range(20):
        assert np.array_equal(agent.act(obs, explore=False), first)
    assert rms.count == count and np.array_equal(rms.mean, mean)  # frozen
    agent.act(obs, explore=True)
    assert rms.count == count + 1  # exploring (training) moves them


def test_checkpoint_round_trip_holds_normalizer_and_rollout():
    env = _pendulum()
    agent = _small_agent()
    _play(agent, env, 140)  # 2 updates, and 12 steps of the next rollout (mid-episode)
    fresh = _small_agent(seed=7)
    fresh.load_state_dict(agent.state_dict(with_buffer=True))
    observations = np.stack([env.reset(seed=s)[0] for s in range(5)])
    for obs in observations:  # the same greedy policy: same networks, same frozen statistics
        assert np.array_equal(fresh.act(obs, explore=False), agent.act(obs, explore=False))
    assert fresh.obs_normalizer.rms.count == agent.obs_normalizer.rms.count
    assert agent.obs_normalizer.rms.count == pytest.approx(140)  # every explored observation
    assert fresh.reward_scaler.rms.count == agent.reward_scaler.rms.count
    assert (fresh.steps, fresh.num_updates, len(fresh.rollouts[0])) == (140, 2, 12)
    assert fresh.resume_notes() == {}
    # the unfinished episode is cut where the checkpoint was: a truncation, bootstrapped
    data = fresh.rollouts[0].take()
    assert data["episode_end"][-1] and data["terminated"][-1] == 0.0

    light = _small_agent(seed=7)  # MLflow's copy holds no rollout by default
    light.load_state_dict(agent.state_dict())
    assert len(light.rollouts[0]) == 0
    assert "12 steps" in light.resume_notes()[ROLLOUT_RESTART_TAG]


def test_a_non_finite_loss_skips_the_steps_and_training_continues():
    env = _pendulum()
    agent = _small_agent(normalize_reward=False)
    before = [p.detach().clone() for p in agent.params]
    metrics = _play(agent, env, 64, reward_override=float("nan"))[-1]
    assert metrics["health/skipped_updates"].item() == 2 * 4  # every minibatch step of the rollout
    assert all(torch.equal(p, b) for p, b in zip(agent.params, before, strict=True))
    metrics = _play(agent, env, 64)[-1]  # a clean rollout learns again
    assert metrics["health/skipped_in_a_row"].item() == 0
    assert all(torch.isfinite(p).all() for p in agent.params)
    assert not all(torch.equal(p, b) for p, b in zip(agent.params, before, strict=True))


def test_learning_rate_anneals_linearly_over_the_run():
    agent = _small_agent(total_steps=256)  # 4 updates
    lrs = [m["train/lr"].item() for m in _play(agent, _pendulum(), 256)]
    np.testing.assert_allclose(lrs, [3e-4, 2.25e-4, 1.5e-4, 0.75e-4])


def test_rollout_hands_out_episodes_and_keeps_the_unfinished_one():
    rollout = Rollout()
    for i, end in enumerate([False, True, False, False, True, False]):
        rollout.add(end, x=float(i))
    first, second = rollout.pop_episodes()
    assert first["x"].tolist() == [0, 1] and second["x"].tolist() == [2, 3, 4]
    assert len(rollout) == 1 and rollout.num_episodes == 0


def test_config_checks():
    with pytest.raises(ConfigError, match="population=2 is not allowed with algo=ppo"):
        validate(compose_cfg(["algo=ppo", "env=pendulum", "population=2"]))
    with pytest.raises(ConfigError, match=r"algo.n_minibatches=32 .* at most algo.n_steps \(16\)"):
        validate(compose_cfg(["algo=ppo", "env=pendulum", "algo.n_steps=16"]))
    with pytest.raises(ConfigError, match="algo.gae_lambda=1.5"):
        validate(compose_cfg(["algo=ppo", "env=pendulum", "algo.gae_lambda=1.5"]))


# --- runs: what is reported, evaluate and collect on a PPO policy, resume ---------------------
@pytest.fixture(scope="module")
def ppo_run(tmp_path_factory, _empty_store_file):
    """A tiny PPO run on Pendulum (normalization on), recording the rewards the trainer hands it;
    and a tiny REINFORCE run beside it, to compare with."""
    store = new_store(tmp_path_factory.mktemp("ppo"), _empty_store_file)
    episodes, current = [], []

    def observe(self, t: Transition):
        current.append(t.reward)
        if t.episode_over:
            episodes.append(sum(current))
            current.clear()
        original(self, t)

    original = PPO.observe
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(PPO, "observe", observe)
        train(compose_cfg(["algo=ppo", "env=pendulum", *TINY, *SMALL, *store["overrides"]]))
    (run,) = all_runs(store["client"])
    train(compose_cfg(["algo=reinforce", "env=pendulum", *TINY, *store["overrides"]]))
    return {**store, "run": run, "env_returns": episodes}


def test_reported_training_returns_are_the_envs_own(ppo_run):
    run_id = ppo_run["run"].info.run_id
    history = ppo_run["client"].get_metric_history(run_id, "train/episode_return")
    assert len(history) == 3  # 600 steps of 200-step episodes
    np.testing.assert_allclose([m.value for m in history], ppo_run["env_returns"], rtol=1e-6)
    assert max(m.value for m in history) < -100  # Pendulum's scale, not the scaled rewards'


def test_evaluate_replays_the_final_evaluation_with_the_frozen_statistics(ppo_run, tmp_path):
    from walkers.training.checkpoint_evaluation import evaluate

    run = ppo_run["run"]
    final = ppo_run["client"].get_metric_history(run.info.run_id, "eval/return_mean")[-1]
    result = evaluate(
        compose_cfg(
            [
                f"run_id={run.info.run_id}",
                "checkpoint=last",
                "episodes=1",
                "start_states=run",  # the final evaluation's own start state
                "video=false",
                "log_to_run=false",
                f"out={tmp_path}",
                *ppo_run["overrides"],
            ],
            config_name="evaluate",
        )
    )
    # exactly on a CPU (same statistics, same kernels); a GPU's kernels read -930.39435772 against
    # -930.39435715 for the same policy and start state
    exact = 0 if not torch.cuda.is_available() else 1e-6
    assert final.step == 600 and result["return_mean"] == pytest.approx(final.value, rel=exact)
    last = ppo_run["path"] / "work" / "runs" / run.info.run_id / "checkpoints" / "last.pt"
    state = read_checkpoint(last)
    assert state["agent"]["obs_normalizer"]["count"] == pytest.approx(600, abs=1)


def test_collect_records_a_ppo_policy(ppo_run, monkeypatch):
    from walkers.training.dataset_recording import collect

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(ppo_run["path"] / "minari"))
    stats = collect(
        compose_cfg(
            [
                f"run_id={ppo_run['run'].info.run_id}",
                "checkpoint=last",
                "episodes=2",
                "random_episodes=1",
                "dataset=walkers/pendulum/ppo-tiny",
                "log_to_mlflow=false",
                *ppo_run["overrides"],
            ],
            config_name="collect",
        )
    )
    assert stats["episodes"] == 2 and stats["steps"] == 400


def test_compare_takes_ppo_like_the_others(ppo_run, tmp_path):
    from walkers.analysis.comparison import compare

    cfg = [
        "env=pendulum",
        "algos=[ppo,reinforce]",
        f"out={tmp_path}",
        "n_resamples=200",
        "log_report=false",
        *ppo_run["overrides"],
    ]
    comparison, out, _ = compare(compose_cfg(cfg, config_name="compare"))
    assert [(a.algo, len(a.runs)) for a in comparison.algos] == [("ppo", 1), ("reinforce", 1)]
    assert "on Pendulum-v1" in (out / "report.md").read_text()


@pytest.mark.slow  # `make test-slow`
def test_resume_continues_the_rollout_and_the_learning_rate_schedule(store):
    args = ["algo=ppo", "env=pendulum", "total_steps=400", "eval_every=200", "eval_episodes=1"]
    args += ["checkpoint_every=200", "log_every=100", "progress=false", "algo.n_steps=96"]
    args += ["algo.n_minibatches=4", "algo.n_epochs=2"]
    first = run_cli([*args, *store["overrides"]], cwd=store["path"])
    assert first.returncode == 0, first.stderr[-2000:]
    (run,) = all_runs(store["client"])
    resumed = run_cli(
        [f"resume={run.info.run_id}", "total_steps=800", *store["overrides"]], cwd=store["path"]
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED" and ROLLOUT_RESTART_TAG not in run.data.tags
    path = store["client"].download_artifacts(
        run.info.run_id, "checkpoints/last.pt", str(store["path"] / "final")
    )
    agent = read_checkpoint(path)["agent"]
    # updates at steps 96, ..., 768; the 16 steps collected before the resume were kept:
    # (800 - 384) - 4 * 96 = 32 steps are waiting (16 + 416 - 384), not (800 - 400) % 96 = 16
    assert (agent["steps"], agent["num_updates"], agent["rollout_steps"]) == (800, 8, 32)
    lrs = [m.value for m in store["client"].get_metric_history(run.info.run_id, "train/lr")]
    # the annealing follows the new budget: the last update (k = 7 of 8) at 3e-4 / 8
    assert lrs[-1] == pytest.approx(3e-4 / 8)


# --- learning ---------------------------------------------------------------------------------
@pytest.mark.slow  # `make test-slow`
def test_ppo_learns_inverted_pendulum(store):
    # Random actions balance the pole for ~6 steps (return ~6); the maximum is 1000. The reference
    # defaults (2048-step rollouts, normalization on), 30k steps, annealed over them. Measured
    # (seed 0, one thread, torch 2.13 CPU): evaluations every 2k steps 24.2 (the initial policy),
    # 46, 72, 85, 96, 238, 646, then 1000 from step 14k to the end; ~20 s. (With value clipping,
    # the default until 2026-11-26: 43, 63, 103, 109, 417, 213, 171, 414, then 1000 from 20k.)
    train(
        compose_cfg(
            [
                "algo=ppo",
                "env=inverted_pendulum",
                "seed=0",
                "total_steps=30000",
                "eval_every=2000",  # the first evaluation is the initial policy's (no update yet)
                "eval_episodes=5",
                "checkpoint_every=30000",
                "progress=false",
                *store["overrides"],
            ]
        )
    )
    (run,) = all_runs(store["client"])
    history = store["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    evals = [m.value for m in history]
    print(evals)
    assert evals[0] < 100, evals  # the initial policy falls early ...
    assert evals[-1] >= 900 and evals[-1] >= 10 * evals[0], evals  # ... the final one balances
