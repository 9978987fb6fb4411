"""Every option of every config group composes, and the CLI's --help / --cfg work."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from tests.conftest import compose_cfg, run_cli
from walkers import PROJECT_ROOT
from walkers.validate import validate

GROUPS = {
    group: sorted(p.stem for p in (PROJECT_ROOT / "conf" / group).glob("*.yaml"))
    for group in ("algo", "env", "tracking", "experiment")
}


@pytest.mark.parametrize("algo", GROUPS["algo"])
@pytest.mark.parametrize("env", GROUPS["env"])
def test_every_algo_env_pair_composes_and_validates(algo, env):
    cfg = compose_cfg([f"algo={algo}", f"env={env}"])
    assert cfg.algo.name == algo
    assert "_target_" in cfg.algo
    assert {"id", "max_episode_steps", "kwargs", "threshold"} <= set(cfg.env)
    validate(cfg)
    OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves


@pytest.mark.parametrize("tracking", GROUPS["tracking"])
def test_tracking_options_compose(tracking):
    cfg = compose_cfg([f"tracking={tracking}"])
    assert cfg.tracking.uri and cfg.tracking.experiment


def test_defaults_are_the_td3_reference_setup(monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cfg = compose_cfg([])
    assert (cfg.algo.name, cfg.env.id, cfg.total_steps) == ("td3", "Walker2d-v5", 1_000_000)
    assert (cfg.eval_every, cfg.eval_episodes) == (5000, 10)
    assert cfg.optimized_metric == "final/return_last10"
    assert cfg.tracking.uri == "sqlite:///mlflow.db" and cfg.tracking.experiment == "walkers"
    a = cfg.algo
    assert list(a.hidden_sizes) == [256, 256]
    assert (a.lr, a.batch_size, a.learning_starts, a.gamma, a.tau) == (
        3e-4,
        256,
        25_000,
        0.99,
        0.005,
    )
    assert (a.policy_noise, a.noise_clip, a.policy_delay) == (0.2, 0.5, 2)
    assert (a.exploration_noise, a.buffer_size) == (0.1, 1_000_000)


def test_tracking_uri_follows_the_environment_variable(monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://tracking.example:5000")
    assert compose_cfg([]).tracking.uri == "http://tracking.example:5000"


def test_cli_help_and_cfg_job(tmp_path):
    help_ = run_cli(["--help"], cwd=tmp_path)
    assert help_.returncode == 0, help_.stderr
    assert "algo: " + ", ".join(GROUPS["algo"]) in help_.stdout  # the menu of config groups
    assert "env: " + ", ".join(GROUPS["env"]) in help_.stdout
    job = run_cli(["--cfg", "job", "algo=td3", "env=pendulum", "seed=3"], cwd=tmp_path)
    assert job.returncode == 0, job.stderr
    cfg = OmegaConf.create(job.stdout)
    assert cfg.seed == 3 and cfg.env.id == "Pendulum-v1" and cfg.algo.name == "td3"


@pytest.mark.parametrize("experiment", GROUPS["experiment"])
def test_experiment_presets_compose(experiment):
    cfg = compose_cfg([f"experiment={experiment}"])
    validate(cfg)
