"""The soft actor-critics of walkers/agents/sac.py: the squashed Gaussian's math, the
temperature; for SAC and CrossQ, which share SoftActorCritic, reproducibility, populations and
checkpoints (CrossQ's with its normalization's running statistics; the NaN guard, compile and
member k = seed k are every algorithm's, in test_shared_properties.py); SAC's
resume through the CLI, and learning Pendulum (whose policy is then replayed by walkers.evaluate
and recorded by walkers.collect). CrossQ's own parts are in test_crossq.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

from tests.conftest import TINY, all_runs, compose_cfg, feed_members, new_store, run_cli
from walkers.agents.common.health import skip_nonfinite
from walkers.agents.common.networks import EnsembleGaussianActor, tanh_log_det_jacobian
from walkers.agents.crossq import CrossQ
from walkers.agents.factory import defaults_for
from walkers.agents.sac import SAC
from walkers.train import train
from walkers.training.checkpoint_evaluation import evaluate
from walkers.training.dataset_recording import collect
from walkers.training.envs import make_env
from walkers.training.run import agent_from_checkpoint, read_checkpoint

TINY_REPLAY = {
    "batch_size": 16,
    "learning_starts": 20,
    "hidden_sizes": [16, 16],
    "buffer_size": 1000,
}
SMALL = defaults_for(SAC, **TINY_REPLAY)
#: CrossQ small, its renormalization past its warm-up within feed_members()'s 41 updates
SMALL_CROSSQ = defaults_for(
    CrossQ, **TINY_REPLAY, critic_hidden_sizes=[16, 16], renorm_warmup_steps=30, policy_delay=2
)
SOFT = pytest.mark.parametrize("cls", [SAC, CrossQ], ids=["sac", "crossq"])
OBS = 3


def small(cls) -> dict:
    return SMALL if cls is SAC else SMALL_CROSSQ


def parameters(agent: SAC) -> dict[str, torch.Tensor]:
    """Every per-member module's state (weights, targets, the temperature; CrossQ's running
    statistics), by name."""
    modules = [n for n in agent.member_cuts(0) if isinstance(getattr(agent, n), torch.nn.Module)]
    return {
        f"{name}.{key}": value
        for name in modules
        for key, value in getattr(agent, name).state_dict().items()
    }


# --- the math ------------------------------------------------------------------------------------
def test_squashed_log_prob_is_the_change_of_variables_through_tanh():
    torch.manual_seed(0)
    low, high = torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 1.0])
    actor = EnsembleGaussianActor(3, 4, 2, [8], low, high).double()
    obs, eps = torch.randn(3, 5, 4, dtype=torch.float64), torch.randn(3, 5, 2, dtype=torch.float64)
    action, log_prob = actor.sample(obs, eps)
    mean, log_std = actor.distribution(obs)
    u = mean + log_std.exp() * eps
    # by hand: log N(u; mu, sigma) - sum_k log(1 - tanh(u_k)^2)
    by_hand = Normal(mean, log_std.exp()).log_prob(u) - torch.log(1 - torch.tanh(u) ** 2)
    torch.testing.assert_close(log_prob, by_hand.sum(-1))
    # torch.distributions: the same Gaussian pushed through tanh
    squashed = TransformedDistribution(Normal(mean, log_std.exp()), [TanhTransform(cache_size=1)])
    torch.testing.assert_close(log_prob, squashed.log_prob(torch.tanh(u)).sum(-1))
    # scaled onto the bounds; the greedy action is tanh(mean), scaled
    torch.testing.assert_close(action, torch.tanh(u) * (high - low) / 2 + (high + low) / 2)
    torch.testing.assert_close(actor(obs), torch.tanh(mean) * (high - low) / 2 + (high + low) / 2)
    assert (-20 <= log_std).all() and (log_std <= 2).all()


def test_the_tanh_correction_is_finite_where_the_naive_formula_is_not():
    u = torch.tensor([-30.0, -5.0, 0.0, 0.5, 5.0, 30.0])
    stable = tanh_log_det_jacobian(u)
    assert torch.isfinite(stable).all()
    naive = torch.log(1 - torch.tanh(u.double()) ** 2)  # float64 still fine at |u| = 5
    torch.testing.assert_close(stable[1:5].double(), naive[1:5], rtol=1e-5, atol=1e-5)
    assert torch.isinf(torch.log(1 - torch.tanh(u) ** 2)[[0, -1]]).all()  # float32, |u| = 30
    torch.testing.assert_close(stable[[0, -1]], 2 * (math.log(2) - 30.0) * torch.ones(2))


def test_the_temperature_rises_when_entropy_is_below_target_and_falls_above():
    agent = SAC(OBS, [-1.0, -1.0], [1.0, -0.5], population=2, seed=0, **SMALL)
    assert agent.target_entropy == -2.0  # -|A|
    before = agent.temperature().clone()
    # member 0's samples are too certain (entropy -log pi = -5 < -2), member 1's too random (+3)
    log_pi = torch.stack([torch.full((16,), 5.0), torch.full((16,), -3.0)])
    loss = agent.temperature_loss(log_pi)
    grad = torch.autograd.grad(loss.sum(), agent.temperature.log_alpha)[0]
    assert grad[0] < 0 < grad[1]  # dJ/dlog(alpha) = -(log pi + target)
    loss = agent.temperature_loss(log_pi)  # the step, as the update takes it
    agent.alpha_optimizer.zero_grad(set_to_none=True)
    loss.sum().backward()
    assert skip_nonfinite(agent.alpha_optimizer, loss).tolist() == [0.0, 0.0]
    agent.alpha_optimizer.step()
    after = agent.temperature()
    assert after[0] > before[0] and after[1] < before[1]
    metrics = agent.entropy_metrics(loss, after, log_pi)
    torch.testing.assert_close(metrics["train/entropy"], torch.tensor([-5.0, 3.0]))


# --- the agent -----------------------------------------------------------------------------------
@SOFT
def test_same_seed_same_run_other_seed_other_run(cls):
    def run(seed):
        agent = cls(OBS, [-2.0], [2.0], seed=seed, **small(cls))
        feed_members(agent, terminate_every=37)
        return agent, agent.act(np.ones(OBS), explore=True)

    (a, action_a), (b, action_b), (c, action_c) = run(0), run(0), run(1)
    assert a.num_updates > 30
    for key, value in parameters(a).items():
        assert torch.equal(value, parameters(b)[key]), key
    assert np.array_equal(action_a, action_b) and not np.array_equal(action_a, action_c)
    assert not torch.equal(a.actor.layers[0].weight, c.actor.layers[0].weight)
    greedy = a.act(np.ones(OBS), explore=False)  # the mean action: the same every call
    assert np.array_equal(greedy, a.act(np.ones(OBS), explore=False)) and abs(greedy[0]) <= 2


@SOFT
def test_a_checkpoint_continues_the_same_experiment(cls):
    original = cls(OBS, [-2.0], [2.0], seed=0, **small(cls))
    feed_members(original, terminate_every=37)
    state = original.state_dict(with_buffer=True)
    assert {"temperature", "alpha_optimizer"} <= set(state) and "actor_target" not in state
    assert ("critic_target" in state) == (cls is SAC)  # CrossQ has no target networks
    restored = cls(OBS, [-2.0], [2.0], seed=9, **small(cls))  # another seed, fresh optimizers
    restored.load_state_dict(state)
    for agent in (original, restored):  # the update's noise streams came with the state
        feed_members(agent, steps=30, terminate_every=37)
    for key, value in parameters(original).items():
        assert torch.equal(value, parameters(restored)[key]), key
    alpha_moments = [s["exp_avg"] for s in restored.alpha_optimizer.state.values()]
    assert alpha_moments and torch.equal(
        alpha_moments[0], next(iter(original.alpha_optimizer.state.values()))["exp_avg"]
    )


@SOFT
def test_population_members_cut_out_and_loaded_back(cls):
    population = cls(OBS, [-2.0], [2.0], population=3, seed=0, **small(cls))
    feed_members(population, terminate_every=37)
    alphas = population.temperature()
    assert len(set(alphas.tolist())) == 3  # each member tunes its own temperature
    single = cls(OBS, [-2.0], [2.0], seed=2, **small(cls))
    single.load_state_dict(population.member_state_dict(2, with_buffer=True))
    obs = np.array([0.1, -0.3, 0.7])
    np.testing.assert_allclose(
        single.act(obs, explore=False), population.member_policy(2).act(obs), atol=1e-6
    )
    assert single.temperature().item() == alphas[2].item()
    assert len(single.buffer) == 60 and single.update()  # it keeps learning on its own

    rebuilt = cls(OBS, [-2.0], [2.0], population=3, seed=7, **small(cls))
    for i in range(3):
        rebuilt.load_member_state_dict(i, population.member_state_dict(i, with_buffer=True))
    for agent in (population, rebuilt):  # the members' noise streams came with their states
        feed_members(agent, steps=30, terminate_every=37)
    for key, value in parameters(population).items():
        assert torch.equal(value, parameters(rebuilt)[key]), key


# --- through the entrypoints ---------------------------------------------------------------------
SAC_TINY = [
    "algo=sac",
    "algo.learning_starts=200",
    "algo.batch_size=64",
    "algo.hidden_sizes=[32,32]",
]
#: What SAC logs of its update (beside the design's metrics).
SAC_METRICS = {
    "loss/critic",
    "loss/actor",
    "loss/alpha",
    "train/alpha",
    "train/entropy",
    "train/q_mean",
    "health/skipped_updates",
    "health/skipped_in_a_row",
}


@pytest.mark.slow  # `make test-slow`
def test_a_resume_through_the_cli_continues_the_run(store):
    first = run_cli([*SAC_TINY, "env=pendulum", *TINY, *store["overrides"]], cwd=store["path"])
    assert first.returncode == 0, first.stderr[-2000:]
    (run,) = all_runs(store["client"])
    run_id, work = run.info.run_id, store["path"] / "work" / "runs" / run.info.run_id
    before = read_checkpoint(work / "resume" / "last.pt")["agent"]
    resumed = run_cli(
        [f"resume={run_id}", "total_steps=900", *store["overrides"]], cwd=store["path"]
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "without the replay buffer" not in resumed.stdout + resumed.stderr
    (run,) = all_runs(store["client"])
    assert run.info.status == "FINISHED"
    evals = [m.step for m in store["client"].get_metric_history(run_id, "eval/return_mean")]
    assert evals == [300, 600, 900]
    alphas = [m.step for m in store["client"].get_metric_history(run_id, "train/alpha")]
    assert alphas == sorted(set(alphas)) and alphas[-1] == 900  # no step logged twice
    after = read_checkpoint(work / "resume" / "last.pt")["agent"]
    assert after["num_updates"] == before["num_updates"] + 300
    assert after["buffer"]["size"] == 900
    (alpha_state,) = after["alpha_optimizer"]["state"].values()
    assert alpha_state["step"].item() == after["num_updates"]  # Adam's count carried over
    assert not torch.equal(after["temperature"]["log_alpha"], before["temperature"]["log_alpha"])


def test_a_population_trains_and_each_member_resumes_alone(store):
    train(compose_cfg([*SAC_TINY, "env=pendulum", "population=2", *TINY, *store["overrides"]]))
    runs = sorted(all_runs(store["client"]), key=lambda r: r.data.params["seed"])
    assert [r.data.tags["walkers.population_member"] for r in runs] == ["0", "1"]
    assert all(SAC_METRICS <= set(r.data.metrics) for r in runs)
    assert runs[0].data.metrics["train/alpha"] != runs[1].data.metrics["train/alpha"]
    member = runs[1].info.run_id
    train(
        compose_cfg([f"resume={member}", "total_steps=700", *store["overrides"]]),
        ["total_steps=700"],
    )
    steps = [m.step for m in store["client"].get_metric_history(member, "eval/return_mean")]
    assert steps == [300, 600, 700]


# --- learning ------------------------------------------------------------------------------------
PENDULUM_SAC = [
    "algo=sac",
    "env=pendulum",
    "seed=0",
    "total_steps=6000",
    "eval_every=2000",
    "eval_episodes=5",
    "checkpoint_every=6000",
    "algo.learning_starts=1000",
    "algo.hidden_sizes=[64,64]",
    "algo.lr=1e-3",  # RL-Zoo's Pendulum-v1 setting: 3e-4 learns too, in more steps
    "progress=false",
]


@pytest.fixture(scope="module")
def pendulum_sac(tmp_path_factory, _empty_store_file) -> dict:
    store = new_store(tmp_path_factory.mktemp("pendulum_sac"), _empty_store_file)
    train(compose_cfg([*PENDULUM_SAC, *store["overrides"]]))
    (run,) = all_runs(store["client"])
    return {**store, "run": run}


@pytest.mark.slow  # `make test-slow`
def test_sac_learns_pendulum(pendulum_sac):
    """A random policy scores about -1200 on Pendulum-v1; a swing-up policy about -150.

    Measured (one thread, 2-core machine, about 20 s): evals at 2k/4k/6k steps -1532, -151, -120
    for seed 0; seeds 1 and 2: -1639, -274, -148 and -1775, -207, -142. With the paper's lr 3e-4
    seed 0 reaches -182 at 4k, but seed 1 only -547 at 8k.
    """
    client, run_id = pendulum_sac["client"], pendulum_sac["run"].info.run_id
    history = [m.value for m in client.get_metric_history(run_id, "eval/return_mean")]
    print(history)
    assert history[0] < -900, history  # it started from a poor policy ...
    # ... and learned to swing up. The best later evaluation, not the last: on a GPU (other random
    # streams) seed 0 read -1602, -149, -463, a swing-up learned and then wobbling at 6k steps
    assert max(history[1:]) >= -300, history
    alpha = [m.value for m in client.get_metric_history(run_id, "train/alpha")]
    assert alpha[-1] < alpha[0]  # the temperature fell as the policy learned to commit


@pytest.mark.slow  # `make test-slow`
def test_evaluate_and_collect_take_a_sac_policy(pendulum_sac, tmp_path, monkeypatch):
    store, run = pendulum_sac, pendulum_sac["run"]
    best = max(
        m.value for m in store["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    )
    replay = evaluate(
        compose_cfg(
            [
                f"run_id={run.info.run_id}",
                "checkpoint=best",
                "episodes=5",
                "start_states=run",  # the best evaluation's own start states
                "video=false",
                f"out={tmp_path}",
                *store["overrides"],
            ],
            config_name="evaluate",
        )
    )
    assert replay["return_mean"] == pytest.approx(best, abs=1e-3)  # the mean action: deterministic
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    stats = collect(
        compose_cfg(
            [
                f"run_id={run.info.run_id}",
                "episodes=3",
                "random_episodes=2",
                "dataset=walkers/pendulum/sac-test",
                "log_to_mlflow=false",
                *store["overrides"],
            ],
            config_name="collect",
        )
    )
    assert stats["episodes"] == 3
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": 200}, shaping=False)
    state = read_checkpoint(
        store["client"].download_artifacts(run.info.run_id, "checkpoints/last.pt", str(tmp_path))
    )
    run_cfg, agent = agent_from_checkpoint(state, env, "cpu")
    assert run_cfg.algo.name == "sac" and isinstance(agent, SAC)
    env.close()
