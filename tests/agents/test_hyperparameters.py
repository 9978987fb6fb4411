"""Each hyperparameter declared once (walkers/agents/declarations/schemas.py): the yaml menus are
written from the declarations, the config check is derived from them, and the agents' constructors
carry no defaults of their own. The run's own settings likewise (walkers/training/settings.py): the
block of conf/train.yaml is written from them and the config check derived."""

from __future__ import annotations

import importlib
import inspect
import shutil
import subprocess
import sys
from dataclasses import fields

import pytest
from hydra.utils import get_class
from omegaconf import OmegaConf

from tests.conftest import compose_cfg
from walkers import PROJECT_ROOT
from walkers.agents.ddpg import DDPG
from walkers.agents.declarations.menus import menu, write_menus
from walkers.agents.declarations.schemas import SCHEMAS
from walkers.agents.factory import defaults_for
from walkers.agents.td3 import TD3
from walkers.errors import ConfigError
from walkers.training.settings import (
    HELP_YAML,
    RunSettings,
    train_yaml,
    validate,
    write_help_yaml,
    write_train_yaml,
)

DECLARED = [(name, f.name) for name, schema in SCHEMAS.items() for f in fields(schema)]
SETTINGS = {f.name: f for f in fields(RunSettings)}


@pytest.mark.parametrize(
    ("schema", "key", "built"),
    [
        ("ddpg", "critic_architecture", "walkers.agents.common.networks.CRITIC_ARCHITECTURES"),
        ("ddpg", "noise_type", "walkers.agents.common.actor_critic.NOISE_TYPES"),
        ("ppo", "activation", "walkers.agents.common.policies.ACTIVATIONS"),
        ("dt", "precision", "walkers.agents.base.PRECISIONS"),
        ("td3", "precision", "walkers.agents.base.PRECISIONS"),
    ],
)
def test_a_menu_of_names_offers_what_the_code_builds(schema, key, built):
    """The declarations name the choices (so that checking a config imports no torch); the
    torch code maps the same names to what it builds, in the same order."""
    module, name = built.rsplit(".", 1)
    offered = next(f for f in fields(SCHEMAS[schema]) if f.name == key).metadata["allowed"]
    assert offered.text == " or ".join(getattr(importlib.import_module(module), name))


@pytest.mark.parametrize(
    "module", ["walkers.agents.declarations.menus", "walkers.training.settings"]
)
def test_the_menus_are_written_from_the_declarations(module):
    assert write_menus(check=True) == []
    assert write_train_yaml(check=True) == []
    assert write_help_yaml(check=True) == []  # walkers.train --help
    result = subprocess.run(
        [sys.executable, "-m", module, "--check"],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_a_menu_edited_by_hand_is_found_and_rewritten(tmp_path):
    shutil.copytree(PROJECT_ROOT / "conf" / "algo", tmp_path / "algo")
    td3 = tmp_path / "algo" / "td3.yaml"
    td3.write_text(td3.read_text().replace("policy_delay: 2 ", "policy_delay: 3 "))
    assert write_menus(tmp_path, check=True) == [str(td3)]
    assert "policy_delay: 3" in td3.read_text()  # a check writes nothing
    assert write_menus(tmp_path) == [str(td3)]
    assert write_menus(tmp_path, check=True) == []
    assert td3.read_text() == menu(SCHEMAS["td3"])


def test_a_run_setting_edited_by_hand_is_found_and_rewritten(tmp_path):
    train = tmp_path / "train.yaml"
    shutil.copy(PROJECT_ROOT / "conf" / "train.yaml", train)
    declared = train.read_text()
    train.write_text(declared.replace("\neval_episodes: 10 ", "\neval_episodes: 5 "))
    assert write_train_yaml(tmp_path, check=True) == [str(train)]
    assert "eval_episodes: 5" in train.read_text()  # a check writes nothing
    assert write_train_yaml(tmp_path) == [str(train)]
    assert train.read_text() == declared == train_yaml(declared)
    with pytest.raises(ValueError, match="no line"):  # the block's heading is kept by hand
        train_yaml(declared.replace("# The run's own settings", "# settings"))


def test_the_help_is_written_from_the_declarations_and_train_yaml(tmp_path):
    """conf/hydra/help/train.yaml follows from the declared settings and conf/train.yaml alone:
    written beside a copy of train.yaml it is the project's; a group added to the defaults list
    puts the help out of step until `make menus`."""
    help_yaml = PROJECT_ROOT / "conf" / HELP_YAML
    train = tmp_path / "train.yaml"
    shutil.copy(PROJECT_ROOT / "conf" / "train.yaml", train)
    assert write_help_yaml(tmp_path) == [str(tmp_path / HELP_YAML)]
    assert (tmp_path / HELP_YAML).read_text() == help_yaml.read_text()
    train.write_text(
        train.read_text().replace("  - ab: null", "  - extra: null  # a new group\n  - ab: null")
    )
    assert write_help_yaml(tmp_path, check=True) == [str(tmp_path / HELP_YAML)]
    write_help_yaml(tmp_path)
    assert "extra=null" in (tmp_path / HELP_YAML).read_text()
    assert "${walkers.options:extra," in (tmp_path / HELP_YAML).read_text()


def test_the_composed_run_settings_are_the_declared_ones():
    """The top level of conf/train.yaml holds each declared setting with its declared default
    (as written: work_dir reads an environment variable); an algorithm's menu that sets run
    settings (dt's gradient-step budget) or follows one (ppo's schedule) names declared ones."""
    cfg = OmegaConf.to_container(compose_cfg([]), resolve=False)
    default = RunSettings()
    for key in SETTINGS:
        assert cfg[key] == getattr(default, key), key
    assert RunSettings.of(compose_cfg(["seed=7"])).seed == 7
    for schema in SCHEMAS.values():
        for key, (value, _) in schema.RUN_SETTINGS.items():
            allowed = SETTINGS[key].metadata["allowed"]
            assert allowed is None or allowed.ok(value), (schema.NAME, key)
        assert {f.metadata["follows"] for f in fields(schema)} - {""} <= set(SETTINGS)


@pytest.mark.parametrize("key", [k for k, f in SETTINGS.items() if f.metadata["allowed"]])
def test_every_checked_run_setting_is_checked_in_one_line(key):
    cfg = compose_cfg(["env=pendulum", "total_steps=1000", "eval_every=500"])
    cfg[key] = "bad"
    with pytest.raises(ConfigError) as error:
        validate(cfg)
    assert str(error.value) == (
        f"{key}='bad' is not allowed: must be {SETTINGS[key].metadata['allowed'].text}"
    )


@pytest.mark.parametrize("name", list(SCHEMAS))
def test_the_composed_config_is_the_declared_one(name):
    """Every key of ``algo=<name>`` is declared and every declaration is a key, with the declared
    default (env-dependent ones read from the env when it sets them)."""
    cfg = compose_cfg([f"algo={name}", "env=walker2d"])
    composed = {k: v for k, v in cfg.algo.items() if k not in ("_target_", "name")}
    schema = SCHEMAS[name]
    assert cfg.algo._target_ == schema.AGENT
    declared = {f.name: f for f in fields(schema)}
    assert set(composed) == set(declared)
    default = schema()
    for key, f in declared.items():
        if f.metadata["follows"]:
            assert composed[key] == cfg[f.metadata["follows"]]
        elif f.metadata["env_key"] and f.metadata["env_key"] in cfg.env:
            assert composed[key] == cfg.env[f.metadata["env_key"]]
        else:
            value = composed[key]
            value = (
                list(value) if hasattr(value, "__len__") and not isinstance(value, str) else value
            )
            assert value == getattr(default, key), key


@pytest.mark.parametrize("name,key", DECLARED, ids=[f"{n}.{k}" for n, k in DECLARED])
def test_every_declared_hyperparameter_is_checked_in_one_line(name, key):
    f = {f.name: f for f in fields(SCHEMAS[name])}[key]
    cfg = compose_cfg([f"algo={name}", "env=pendulum", "total_steps=1000", "eval_every=500"])
    cfg.algo[key] = "bad"
    with pytest.raises(ConfigError) as error:
        validate(cfg)
    message = str(error.value)
    assert message == f"algo.{key}='bad' is not allowed: must be {f.metadata['allowed'].text}"


@pytest.mark.parametrize("name", list(SCHEMAS))
def test_the_constructors_take_no_defaults_of_their_own(name):
    """A declared hyperparameter has no default in any constructor that names it: none, or None
    for "not given" (an idea the class turns off, e.g. DDPG's smoothing; TD3 and SAC have no
    separate actor and critic learning rates)."""
    schema = SCHEMAS[name]
    agent_class = get_class(schema.AGENT)
    named = 0
    for cls in agent_class.__mro__:
        if "__init__" not in vars(cls):
            continue
        parameters = inspect.signature(cls.__init__).parameters
        for f in fields(schema):
            if f.name in parameters:
                named += 1
                assert parameters[f.name].default in (inspect.Parameter.empty, None), f.name
    assert named >= len(fields(schema))  # each is a constructor argument somewhere


def test_ddpg_is_td3_without_its_three_ideas():
    """TD3 needs its smoothing and delay; DDPG, which turns them off, refuses them."""
    with pytest.raises(TypeError, match="needs policy_delay"):
        TD3(3, [-1.0], [1.0], **{**defaults_for(TD3)} | {"policy_delay": None})
    with pytest.raises(TypeError, match="'policy_noise'"):
        DDPG(3, [-1.0], [1.0], **defaults_for(DDPG), policy_noise=0.2)
    with pytest.raises(TypeError, match="no hyperparameter 'policy_noise'"):
        defaults_for(DDPG, policy_noise=0.2)


@pytest.mark.parametrize(
    "name,key,bound", [("td3", "batch_size", "buffer_size"), ("ppo", "n_minibatches", "n_steps")]
)
def test_a_hyperparameter_bounded_by_another_is_checked_against_it(name, key, bound):
    cfg = compose_cfg([f"algo={name}", "env=pendulum", "total_steps=1000", "eval_every=500"])
    cfg.algo[key], cfg.algo[bound] = 64, 32
    with pytest.raises(ConfigError, match=rf"^algo.{key}=64 is not allowed: must be at most "
                       rf"algo.{bound} \(32\)"):  # fmt: skip
        validate(cfg)
    cfg.algo[bound] = 64
    validate(cfg)  # equal is allowed


@pytest.mark.parametrize("override", ["+algo.actor_lr=0", "+algo.noise_type=pink"])
def test_a_key_the_algorithm_does_not_declare_is_refused(override):
    """TD3's constructor would take these (the core's and DDPG's knobs); TD3 declares neither."""
    key = override[1:].split("=")[0]
    cfg = compose_cfg(["algo=td3", "env=pendulum", override])
    with pytest.raises(
        ConfigError, match=rf"^{key}=.* td3 has no hyperparameter .*\(.*it has lr, "
    ):
        validate(cfg)


def test_the_checks_follow_the_class_built_not_the_name():
    cfg = compose_cfg(["algo=td3", "env=pendulum", "algo.name=my_td3", "algo.tau=2"])
    with pytest.raises(ConfigError, match=r"algo.tau=2 is not allowed"):
        validate(cfg)


def test_the_train_menu_lists_every_declared_algorithm():
    """conf/train.yaml's defaults list names the algorithms (written by `make menus`): all."""
    line = next(
        x for x in (PROJECT_ROOT / "conf/train.yaml").read_text().splitlines() if "- algo:" in x
    )
    listed = {name.strip() for name in line.split("#")[1].split("(")[0].split("|")}
    assert listed == set(SCHEMAS)
