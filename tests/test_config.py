"""Every option of every config group composes, and the CLI's --help / --cfg work: --help leads
with the run settings and their docs, then every group with its options on disk."""

from __future__ import annotations

import re
from dataclasses import fields

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tests.conftest import CONF_DIR, compose_cfg, run_cli
from walkers import PROJECT_ROOT
from walkers.training.settings import SET_BY_WALKERS, RunSettings, is_offline, validate
from walkers.tuning.trial import make_pruner

GROUPS = {
    group: sorted(p.stem for p in (PROJECT_ROOT / "conf" / group).glob("*.yaml"))
    for group in ("algo", "env", "tracking", "experiment")
}


@pytest.mark.parametrize("algo", GROUPS["algo"])
@pytest.mark.parametrize("env", GROUPS["env"])
def test_every_algo_env_pair_composes_and_validates(algo, env):
    cfg = compose_cfg([f"algo={algo}", f"env={env}"])
    if is_offline(cfg):  # dt, td3bc: validate checks that a dataset is named, not that it exists
        cfg = compose_cfg([f"algo={algo}", f"env={env}", "dataset=walkers/some/dataset-v0"])
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


#: Every config group of walkers.train and its options, as they are on disk: the folders of conf/
#: (Hydra's own, hydra/, aside) and sweeps/, a folder of the top level found through searchpath.
TRAIN_GROUPS = {
    folder.name: sorted(path.stem for path in folder.glob("*.yaml"))
    for folder in [*(PROJECT_ROOT / "conf").iterdir(), PROJECT_ROOT / "sweeps"]
    if folder.is_dir() and folder.name != "hydra"
}


@pytest.fixture(scope="module")
def train_help(tmp_path_factory) -> list[str]:
    """The lines ``python -m walkers.train --help`` prints."""
    result = run_cli(["--help"], cwd=tmp_path_factory.mktemp("help"))
    assert result.returncode == 0, result.stderr
    return result.stdout.splitlines()


def words(lines: list[str]) -> str:
    """``lines`` as one line, each run of spaces one space (the help wraps its docs)."""
    return " ".join(" ".join(lines).split())


def line_of(lines: list[str], start: str) -> int:
    (at,) = [i for i, line in enumerate(lines) if line.startswith(start)]
    return at


def test_help_leads_with_each_run_setting_and_its_doc(train_help):
    assert train_help[0].startswith("python -m walkers.train ")  # not "train is powered by Hydra"
    assert max(len(line) for line in train_help) <= 100, "the help wraps to 100 columns"
    at = {f.name: line_of(train_help, f"{f.name}=") for f in fields(RunSettings)}
    for f in fields(RunSettings):  # the doc beside the setting, as settings.py declares it
        beside = words(train_help[at[f.name] : at[f.name] + 6])
        assert " ".join(f.metadata["doc"].split()) in beside, f.name
    groups = line_of(train_help, "== Config groups")
    internal = [i for i, line in enumerate(train_help) if re.match(r"(trial|pruning)\.", line)]
    run_settings = [i for name, i in at.items() if name not in SET_BY_WALKERS]
    assert max(run_settings) < groups < min(internal)  # the run's own settings first
    assert min(at[name] for name in SET_BY_WALKERS) > groups  # walkers' own keys last
    assert not any("trial." in line for line in train_help[: max(run_settings) + 1])


def test_help_lists_every_config_group_with_its_options_on_disk(train_help):
    assert {"algo", "env", "tracking", "optuna", "pruner", "experiment", "sweeps", "ab"} <= set(
        TRAIN_GROUPS
    )
    groups = line_of(train_help, "== Config groups")
    examples = line_of(train_help, "== Examples")
    for group, options in TRAIN_GROUPS.items():
        at = line_of(train_help, f"{group}=")
        assert groups < at < examples, group
        _, listed = words(train_help[at:]).split(" ", 1)  # after group=default
        assert listed.startswith(", ".join(options)), (group, listed[:200])
    commands = train_help[examples + 1 : examples + 4]
    assert all(line.startswith("python -m walkers.train ") for line in commands), commands


def test_cli_hydra_help_and_cfg_job(tmp_path):
    hydra_help = run_cli(["--hydra-help"], cwd=tmp_path)  # Hydra's own help, as it was
    assert hydra_help.returncode == 0 and "== Flags ==" in hydra_help.stdout, hydra_help.stderr
    job = run_cli(["--cfg", "job", "algo=td3", "env=pendulum", "seed=3"], cwd=tmp_path)
    assert job.returncode == 0, job.stderr
    cfg = OmegaConf.create(job.stdout)
    assert cfg.seed == 3 and cfg.env.id == "Pendulum-v1" and cfg.algo.name == "td3"


@pytest.mark.parametrize("experiment", GROUPS["experiment"])
def test_experiment_presets_compose(experiment):
    cfg = compose_cfg([f"experiment={experiment}"])
    validate(cfg)


def test_presets_override_the_train_defaults():
    assert compose_cfg(["experiment=ab_pendulum"]).total_steps == 10_000
    assert compose_cfg(["sweeps=td3_walker2d"]).total_steps == 300_000


def compose_with_hydra(overrides: list[str]):
    with initialize_config_dir(config_dir=CONF_DIR):
        return compose("train", overrides=overrides, return_hydra_config=True)


def swept(experiment: str, key: str) -> str | None:
    """What an experiment preset's multirun sweeps ``key`` over (hydra.sweeper.params)."""
    cfg = compose_with_hydra([f"experiment={experiment}"])
    return OmegaConf.select(cfg, f"hydra.sweeper.params.{key}", default=None)


# The algo.* keys an A/B preset may set for every arm: small nets in the cheap twins (64-64 is
# REINFORCE's and PPO's own size). Anything else would make an arm other than its algorithm.
AB_PRESET_ALGO_KEYS = {
    "ab_pendulum": {"hidden_sizes"},
    "ab_all_inverted_pendulum": {"hidden_sizes"},
}


@pytest.mark.parametrize("experiment", GROUPS["experiment"])
def test_ab_presets_keep_every_algorithm_its_own_settings(experiment):
    algos = swept(experiment, "algo")
    for algo in algos.split(",") if algos else []:
        cfg = compose_with_hydra([f"experiment={experiment}", f"algo={algo}"])  # one job's config
        validate(cfg)
        mine = OmegaConf.to_container(cfg.algo, resolve=True)
        env = cfg.hydra.runtime.choices.env
        own = compose_cfg([f"algo={algo}", f"env={env}", f"total_steps={cfg.total_steps}"])
        own = OmegaConf.to_container(own.algo, resolve=True)
        changed = {k for k in mine.keys() | own.keys() if mine.get(k) != own.get(k)}
        assert changed <= AB_PRESET_ALGO_KEYS.get(experiment, set()), (algo, changed)
        if algo in ("reinforce", "ppo"):  # their reference nets, whatever the preset
            assert mine["hidden_sizes"] == [64, 64], algo


@pytest.mark.parametrize("experiment", ["ab_walker2d_all", "ab_all_inverted_pendulum"])
def test_the_extended_study_and_its_twin_run_all_five_algorithms_over_5_seeds(experiment):
    assert swept(experiment, "algo") == "reinforce,ppo,ddpg,td3,sac"
    assert swept(experiment, "seed") == "range(5)"
    assert compose_cfg([f"experiment={experiment}"]).tracking.experiment == experiment


SWEEPS = sorted(p.stem for p in (PROJECT_ROOT / "sweeps").glob("*.yaml"))


@pytest.mark.parametrize("sweep", SWEEPS)
def test_sweep_files_compose_with_a_pruner_and_a_search_space(sweep):
    offline = ["dataset=walkers/some/dataset-v0"] if sweep.startswith("dt_") else []
    with initialize_config_dir(config_dir=CONF_DIR):
        cfg = compose("train", overrides=[f"sweeps={sweep}", *offline], return_hydra_config=True)
    validate(cfg)
    assert cfg.hydra.sweeper._target_ == "walkers.plugins.PruningOptunaSweeper"
    assert cfg.hydra.sweeper.study_name == sweep and cfg.hydra.sweeper.params
    assert make_pruner(cfg.pruner) is not None
    absent = object()
    for key in cfg.hydra.sweeper.params:  # every searched key exists in the job config
        assert OmegaConf.select(cfg, key, default=absent) is not absent, key


def test_short_envs_shorten_the_off_policy_warm_up():
    assert compose_cfg(["env=pendulum"]).algo.learning_starts == 1000
    assert compose_cfg(["env=walker2d", "algo=ddpg"]).algo.learning_starts == 25_000


def test_renamed_keys_still_work_for_one_release(capsys):
    from walkers.cli import renamed_overrides

    old = ["sweep/pruner=threshold", "sweep.pruner.lower=-5", "+sweep.warmup_steps=7", "seed=1"]
    new = renamed_overrides(old)
    assert new == ["pruner=threshold", "pruner.lower=-5", "+pruning.warmup_steps=7", "seed=1"]
    assert capsys.readouterr().err.count("note:") == 3
    cfg = compose_cfg(["sweeps=pendulum_tiny", *new[:2]])
    assert cfg.pruner.lower == -5 and cfg.pruner._target_.endswith("ThresholdPruner")
