"""``impl=sb3``: Stable-Baselines3's twins as arms of an ordinary study.

Tiny real runs of each twin through the CLI (logged, evaluated and summarized as walkers runs),
a resume that continues, the hyperparameter mapping read back from the objects SB3 built, the
settings SB3 cannot express refused in one line, and a ``group_by=impl`` report whose verdicts
pair each algorithm with its own twin.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from tests.conftest import (
    DESIGN_METRICS,
    TINY,
    all_runs,
    compose_cfg,
    new_store,
    one_line_error,
    run_cli,
    run_cli_signalled_inside_an_update,
)
from walkers.agents.factory import build_agent
from walkers.analysis.comparison import build_comparison
from walkers.errors import ConfigError
from walkers.train import train
from walkers.training.checkpoint_evaluation import evaluate
from walkers.training.envs import env_spaces, make_env

stable_baselines3 = pytest.importorskip("stable_baselines3")

#: Per algorithm, what makes its tiny Pendulum run learn within 600 steps.
QUICK = {
    "td3": ["algo.learning_starts=100", "algo.batch_size=32"],
    "ddpg": ["algo.learning_starts=100", "algo.batch_size=32"],
    "sac": ["algo.learning_starts=100", "algo.batch_size=32"],
    "crossq": [
        "algo.learning_starts=100",
        "algo.batch_size=32",
        "algo.critic_hidden_sizes=[64,64]",
    ],
    "ppo": ["algo.n_steps=200", "algo.n_minibatches=4", "algo.n_epochs=2"],
}
LOSSES = {
    "td3": {"loss/critic", "loss/actor"},
    "ddpg": {"loss/critic", "loss/actor"},
    "sac": {"loss/critic", "loss/actor", "loss/alpha", "train/alpha"},
    "crossq": {"loss/critic", "loss/actor", "loss/alpha", "train/alpha"},
    "ppo": {"loss/policy", "loss/value", "train/approx_kl", "train/entropy"},
}


def tiny(algo: str, store: dict, *more: str) -> list[str]:
    return [f"algo={algo}", "env=pendulum", *TINY, *QUICK[algo], *store["overrides"], *more]


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """A tiny impl=sb3 run of each of the five twins, and its walkers counterpart for two."""
    store = new_store(tmp_path_factory.mktemp("sb3"))
    for algo in QUICK:
        for seed in (0, 1) if algo in ("td3", "ppo") else (0,):
            for impl in ("sb3", "walkers") if algo in ("td3", "ppo") else ("sb3",):
                train(compose_cfg(tiny(algo, store, f"impl={impl}", f"seed={seed}")))
    return store


def runs_of(store, algo, impl):
    """The runs of ``algo`` trained by ``impl``, by seed."""
    found = [
        r
        for r in all_runs(store["client"])
        if r.data.tags.get("algo") == algo and r.data.params.get("impl") == impl
    ]
    return sorted(found, key=lambda r: int(r.data.params["seed"]))


@pytest.mark.parametrize("algo", list(QUICK))
@pytest.mark.slow  # `make test-slow`
def test_an_sb3_twin_is_logged_and_summarized_as_a_walkers_run(twins, algo):
    run = runs_of(twins, algo, "sb3")[0]
    assert run.info.status == "FINISHED"
    assert run.data.params["impl"] == "sb3" and run.data.tags["impl"] == "sb3"
    assert run.info.run_name == f"{algo}-sb3-Pendulum-v1-s0"
    assert DESIGN_METRICS | LOSSES[algo] <= set(run.data.metrics)
    history = twins["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    assert [m.step for m in history] == [300, 600]
    assert all(math.isfinite(m.value) for m in history)
    episodes = twins["client"].get_metric_history(run.info.run_id, "train/episode_return")
    assert [m.step for m in episodes] == [200, 400, 600]  # Pendulum's 200-step episodes
    artifacts = {a.path for a in twins["client"].list_artifacts(run.info.run_id, "checkpoints")}
    assert {"checkpoints/best.pt", "checkpoints/last.pt"} <= artifacts


@pytest.mark.slow  # `make test-slow`
def test_an_sb3_run_is_replayed_by_walkers_evaluate(twins, tmp_path):
    """PPO's twin acts through its VecNormalize statistics, restored without an env."""
    run = runs_of(twins, "ppo", "sb3")[0]
    common = [f"run_id={run.info.run_id}", "episodes=2", "video=false", f"out={tmp_path}"]
    replay = compose_cfg([*common, "start_states=run", *twins["overrides"]], "evaluate")
    history = twins["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    result = evaluate(replay)
    # best.pt from its own evaluation's start state scores what that evaluation logged
    first = compose_cfg(
        [*common, "start_states=run", "episodes=1", *twins["overrides"]], "evaluate"
    )
    assert evaluate(first)["return_mean"] == pytest.approx(max(m.value for m in history), abs=1e-3)
    assert len(result["returns"]) == 2


@pytest.mark.slow  # `make test-slow`
def test_the_same_seed_trains_the_same_sb3_run(twins, tmp_path):
    store = new_store(tmp_path)
    train(compose_cfg(tiny("td3", store, "impl=sb3", "seed=0")))

    def curve(where):
        run = runs_of(where, "td3", "sb3")[0]
        return [
            m.value for m in where["client"].get_metric_history(run.info.run_id, "eval/return_mean")
        ]

    assert curve(store) == curve(twins)


@pytest.mark.slow  # `make test-slow`
def test_resume_continues_an_sb3_run(tmp_path):
    """Killed at its budget and resumed with a larger one: the same run, SB3's step count and
    replay buffer carried over, no step logged twice; SB3 wrote nothing to the temp dir."""
    store = new_store(tmp_path)
    train(compose_cfg(tiny("sac", store, "impl=sb3")))
    run_id = all_runs(store["client"])[0].info.run_id
    temp = tmp_path / "tmpdir"
    temp.mkdir()
    result = run_cli(
        [f"resume={run_id}", "total_steps=900", *store["overrides"]],
        cwd=tmp_path,
        env_overrides={"TMPDIR": str(temp)},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert not list(temp.glob("SB3-*"))  # SB3's own logger folders (one per learn call)
    log = result.stdout + result.stderr
    assert f"resuming run {run_id} at step 600" in log
    run = store["client"].get_run(run_id)
    assert run.info.status == "FINISHED" and len(all_runs(store["client"])) == 1
    history = store["client"].get_metric_history(run_id, "eval/return_mean")
    assert [m.step for m in history] == [300, 600, 900]
    assert "walkers.buffer_refill" not in run.data.tags  # the local copy had the buffer
    alpha = store["client"].get_metric_history(run_id, "train/alpha")
    assert max(m.step for m in alpha) == 900


@pytest.mark.slow  # `make test-slow`
def test_resume_continues_an_sb3_ppo_run_with_its_normalization(tmp_path):
    """PPO's twin normalizes observations and rewards (VecNormalize): a resume carries on its
    running statistics from the checkpoint, whose pickled state SB3 writes without ``returns``."""
    store = new_store(tmp_path)
    train(compose_cfg(tiny("ppo", store, "impl=sb3")))
    run_id = all_runs(store["client"])[0].info.run_id

    def observations_counted() -> float:
        folder = tmp_path / f"ckpt{len(list(tmp_path.glob('ckpt*')))}"
        folder.mkdir()
        path = store["client"].download_artifacts(run_id, "checkpoints/last.pt", str(folder))
        return torch.load(path, weights_only=False)["agent"]["normalization"]["obs_rms"].count

    counted = observations_counted()
    result = run_cli([f"resume={run_id}", "total_steps=900", *store["overrides"]], cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"resuming run {run_id} at step 600" in result.stdout + result.stderr
    run = store["client"].get_run(run_id)
    assert run.info.status == "FINISHED" and len(all_runs(store["client"])) == 1
    history = store["client"].get_metric_history(run_id, "eval/return_mean")
    assert [m.step for m in history] == [300, 600, 900]
    assert observations_counted() >= counted + 300  # the statistics went on, not from zero


@pytest.mark.faults  # `make test-faults`: a signal, sent by the run to itself
def test_a_stop_inside_sb3s_ppo_update_waits_for_the_update(tmp_path):
    """SIGINT at the 4th of the 8 Adam steps of PPO's first update (200 steps, 4 minibatches, 2
    epochs): SB3's update runs to its end, its loop stops at the next env step (201), and the
    checkpoint holds the whole update (Adam's step count 8), which a resume continues."""
    store = new_store(tmp_path)
    args = tiny("ppo", store, "impl=sb3", "total_steps=1000", "eval_every=500")
    cut = run_cli_signalled_inside_an_update(args, tmp_path, 4)
    assert cut.returncode == 130, cut.stderr[-2000:]
    (run,) = all_runs(store["client"])
    assert run.info.status == "KILLED"
    path = store["client"].download_artifacts(run.info.run_id, "checkpoints/last.pt", str(tmp_path))
    state = torch.load(path, weights_only=False)
    assert state["trainer"]["step"] == 201
    model = stable_baselines3.PPO.load(io.BytesIO(state["agent"]["model"]), device="cpu")
    adam = model.policy.optimizer.state_dict()["state"]
    assert {int(param["step"]) for param in adam.values()} == {8}
    resumed = run_cli([f"resume={run.info.run_id}", *args], cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert store["client"].get_run(run.info.run_id).info.status == "FINISHED"


# --- the mapping, read back from what SB3 built -------------------------------------------------
def twin(algo: str, *overrides: str, env: str = "pendulum"):
    cfg = compose_cfg([f"algo={algo}", f"env={env}", "impl=sb3", "device=cpu", *overrides])
    gym_env = make_env(cfg.env)
    agent = build_agent(cfg, env_spaces(gym_env))
    agent.attach(gym_env, cfg.total_steps)
    return cfg.algo, agent.model, agent


def linear_widths(module) -> list[int]:
    import torch

    return [m.out_features for m in module.modules() if isinstance(m, torch.nn.Linear)]


def test_td3_maps_onto_sb3s_td3():
    hp, model, _ = twin("td3", "algo.hidden_sizes=[64,32]", "algo.lr=1e-3", "algo.policy_delay=3")
    assert isinstance(model, stable_baselines3.TD3)
    assert linear_widths(model.actor) == [64, 32, 1]
    assert linear_widths(model.critic) == [64, 32, 1, 64, 32, 1]  # twin critics
    assert model.actor.optimizer.param_groups[0]["lr"] == 1e-3
    assert model.critic.optimizer.param_groups[0]["lr"] == 1e-3
    assert (model.policy_delay, model.target_policy_noise, model.target_noise_clip) == (
        3,
        hp.policy_noise,
        hp.noise_clip,
    )
    assert (model.batch_size, model.learning_starts, model.tau, model.gamma) == (
        hp.batch_size,
        hp.learning_starts,
        hp.tau,
        hp.gamma,
    )
    assert model.buffer_size == hp.buffer_size and model.gradient_steps == 1
    assert np.allclose(model.action_noise._sigma, hp.exploration_noise)


def test_crossq_maps_onto_sb3_contribs_crossq():
    hp, model, _ = twin("crossq", "algo.critic_hidden_sizes=[96,80]", "algo.renorm_warmup_steps=7")
    from sb3_contrib import CrossQ
    from sb3_contrib.common.torch_layers import BatchRenorm

    assert isinstance(model, CrossQ)
    assert linear_widths(model.critic) == [96, 80, 1, 96, 80, 1]  # twin critics, no targets
    assert linear_widths(model.actor) == [256, 256, 1, 1]  # Pendulum: mean and log-std heads
    for optimizer in (model.actor.optimizer, model.critic.optimizer):
        group = optimizer.param_groups[0]
        assert (group["lr"], group["betas"]) == (hp.lr, tuple(hp.adam_betas))
    renorms = [m for m in model.critic.modules() if isinstance(m, BatchRenorm)]
    assert renorms and {(m.momentum, m.warmup_steps) for m in renorms} == {(0.01, 7)}
    assert (model.policy_delay, model.batch_size, model.gamma) == (3, hp.batch_size, hp.gamma)
    assert model.target_entropy == -1.0 and model.learning_starts == hp.learning_starts


def test_ddpg_maps_onto_sb3s_ddpg_with_ou_noise():
    _, model, _ = twin(
        "ddpg", "algo.noise_type=ou", "algo.hidden_sizes=[32,32]", "algo.critic_hidden_sizes=[48]"
    )
    assert isinstance(model, stable_baselines3.DDPG)
    assert linear_widths(model.actor) == [32, 32, 1]
    assert linear_widths(model.critic) == [48, 1]  # one critic
    # no target smoothing: SB3's DDPG clips its target noise to 0
    assert model.policy_delay == 1 and model.target_noise_clip == 0
    noise = model.action_noise
    assert isinstance(noise, stable_baselines3.common.noise.OrnsteinUhlenbeckActionNoise)
    assert noise._theta == 0.15 and np.allclose(noise._sigma, 0.1)


def test_sac_maps_onto_sb3s_sac():
    _, model, _ = twin("sac", "algo.alpha_init=0.5", "algo.lr=5e-4", env="walker2d")
    assert isinstance(model, stable_baselines3.SAC)
    assert math.exp(model.log_ent_coef.item()) == pytest.approx(0.5)
    assert model.target_entropy == -6  # -|A| of Walker2d
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == 5e-4
    assert linear_widths(model.actor.latent_pi) == [256, 256]


def test_ppo_maps_onto_sb3s_ppo_with_vecnormalize():
    hp, model, agent = twin(
        "ppo",
        "algo.n_steps=1024",
        "algo.n_minibatches=16",
        "algo.vf_coef=0.8",
        "algo.clip_value_loss=true",
    )
    assert isinstance(model, stable_baselines3.PPO)
    assert model.batch_size == 64 and model.n_steps == 1024 and model.n_epochs == hp.n_epochs
    assert model.vf_coef == pytest.approx(0.4)  # SB3's value loss is twice walkers'
    assert model.clip_range(1) == hp.clip_coef and model.clip_range_vf(1) == hp.clip_coef
    assert model.lr_schedule(1.0) == hp.lr and model.lr_schedule(0.25) == pytest.approx(hp.lr / 4)
    assert model.policy.optimizer.defaults["eps"] == hp.adam_eps
    assert linear_widths(model.policy.mlp_extractor.policy_net) == [64, 64]
    assert model.policy.log_std.detach().tolist() == [hp.log_std_init]
    normalize = agent.vec_normalize
    assert (normalize.norm_obs, normalize.norm_reward) == (True, True)
    assert (normalize.clip_obs, normalize.clip_reward, normalize.gamma) == (10.0, 10.0, 0.99)
    _, unclipped, _ = twin("ppo")  # the default: no value clipping, SB3's own default
    assert unclipped.clip_range_vf is None


# --- refused ------------------------------------------------------------------------------------
SB3_CANNOT = [
    (["algo=reinforce", "impl=sb3"], ["impl=sb3", "algo=reinforce", "td3, ddpg, sac, crossq, ppo"]),
    (["algo=dt", "impl=sb3", "dataset=x"], ["algo=dt", "td3, ddpg, sac, crossq, ppo"]),
    (["algo=ppo", "impl=sb3", "algo.target_kl=0.02"], ["algo.target_kl=0.02", "null"]),
    (
        ["algo=ddpg", "impl=sb3", "algo.critic_architecture=layernorm_branch"],
        ["algo.critic_architecture='layernorm_branch'", "mlp"],
    ),
    (["algo=sac", "impl=sb3", "algo.alpha_lr=1e-3"], ["algo.alpha_lr=0.001", "algo.lr"]),
    (["algo=td3", "impl=sb3", "population=2"], ["population=2", "impl=sb3"]),
    (["algo=td3", "impl=sb4"], ["impl='sb4'", "walkers, sb3"]),
]


@pytest.mark.parametrize("overrides, names", SB3_CANNOT, ids=lambda c: " ".join(c))
def test_what_sb3_cannot_express_is_refused_in_one_line(tmp_path, overrides, names):
    store = new_store(tmp_path)
    with pytest.raises(ConfigError) as refused:
        train(compose_cfg(["env=pendulum", *TINY, *overrides, *store["overrides"]]))
    error = str(refused.value)
    assert "\n" not in error and all(name in error for name in names), error
    assert all_runs(store["client"]) == []
    assert not (tmp_path / "work").exists()


def test_a_refusal_reaches_the_command_line_as_one_line_and_exit_2(tmp_path):
    store = new_store(tmp_path)
    overrides, names = SB3_CANNOT[0]
    result = run_cli(["env=pendulum", *overrides, *store["overrides"]], cwd=tmp_path)
    error = one_line_error(result)
    assert all(name in error for name in names), error
    assert all_runs(store["client"]) == []
    assert not (tmp_path / "work").exists()


def test_impl_sb3_without_sb3_installed_says_how_to_install_it(tmp_path):
    """A machine without the extra: ``import stable_baselines3`` fails there."""
    shadow = tmp_path / "no_sb3"
    (shadow / "stable_baselines3").mkdir(parents=True)
    (shadow / "stable_baselines3" / "__init__.py").write_text(
        "raise ImportError(\"No module named 'stable_baselines3'\")\n"
    )
    store = new_store(tmp_path)
    result = run_cli(
        ["algo=td3", "env=pendulum", "impl=sb3", *store["overrides"]],
        cwd=tmp_path,
        env_overrides={"PYTHONPATH": str(shadow)},
    )
    error = one_line_error(result)
    assert "impl=sb3" in error and "pip install -e '.[sb3]'" in error


# --- the report -----------------------------------------------------------------------------------
@pytest.mark.slow  # `make test-slow`
def test_group_by_impl_pairs_each_algorithm_with_its_twin(twins, tmp_path):
    cfg = compose_cfg(
        [
            "env=pendulum",
            "algos=[td3,ppo]",
            "group_by=impl",
            "total_steps=600",
            "n_resamples=200",
            f"out={tmp_path}",
            "log_report=false",
            *twins["overrides"],
        ],
        config_name="compare",
    )
    comparison, _ = build_comparison(cfg)
    names = [r.algo for r in comparison.algos]
    assert len(names) == 4 and all(len(r.runs) == 2 for r in comparison.algos)
    pairs = {(p.a, p.b) for p in comparison.pairs}
    algo_of = {r.algo: r.algorithm for r in comparison.algos}
    assert len(pairs) == 2 and all(algo_of[a] == algo_of[b] for a, b in pairs)
    assert {algo_of[a] for a, _ in pairs} == {"td3", "ppo"}
    impls = {frozenset(OmegaConf.create(r.arm.group_values).values()) for r in comparison.algos}
    assert impls == {frozenset({"sb3"}), frozenset({"walkers"})}
