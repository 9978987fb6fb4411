"""Bad input: one clear line naming the key, value and what is allowed; exit 2; no MLflow run."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import TINY, all_runs, compose_cfg, one_line_error, run_cli
from walkers.cli import exit_on_bad_overrides
from walkers.errors import ConfigError
from walkers.train import train

CASES = [
    # (overrides, words the one-line message must contain)
    (["algo.lr=-1"], ["algo.lr=-1", "> 0"]),
    (["algo.batch_size=0"], ["algo.batch_size=0", "> 0"]),
    (["algo.batch_size=512", "algo.buffer_size=256"], ["algo.batch_size=512", "algo.buffer_size"]),
    (["algo.gamma=1.5"], ["algo.gamma=1.5", "(0, 1]"]),
    (["algo.tau=0"], ["algo.tau=0", "(0, 1]"]),
    (["total_steps=-5"], ["total_steps=-5", "integer > 0"]),
    (["total_steps=10.5"], ["total_steps=10.5", "integer"]),
    (["eval_every=5000", "total_steps=1000"], ["eval_every=5000", "total_steps"]),
    (["device=tpu"], ["device='tpu'", "auto, cpu, cuda"]),
    (["optimized_metric=loss"], ["optimized_metric='loss'", "final/return_last10"]),
    (["env.id=NoSuchEnv-v0"], ["env.id='NoSuchEnv-v0'", "Gymnasium"]),
    (["env.id=CartPole-v1"], ["env.id='CartPole-v1'", "Discrete", "continuous"]),
    (["algo=ddpg", "algo.noise_type=pink"], ["algo.noise_type='pink'", "gaussian", "ou"]),
    (["algo=td3", "+algo.momentum=0.9"], ["algo", "momentum"]),
    (["resume=0123456789abcdef"], ["resume='0123456789abcdef'", "not a run"]),
    (["tracking.uri=nosuchscheme://x"], ["tracking.uri='nosuchscheme://x'", "sqlite"]),
    (["algo.compile=yes"], ["algo.compile='yes'", "true or false"]),
    (["resume="], ["resume=''", "empty", "resume=<run id>"]),  # resume=$RUN_ID, variable unset
    (["resume=[]"], ["resume=[]", "empty"]),
    (["algo=td3", "+algo.lrr=1e-3"], ["algo.lrr=0.001", "did you mean 'lr'?", "batch_size"]),
]


def contents(folder: Path) -> set[str]:
    """Every file and folder under ``folder``, as paths relative to it."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.mark.parametrize("overrides,expected", CASES, ids=[" ".join(c[0]) for c in CASES])
def test_bad_value_is_rejected_before_any_run(store, overrides, expected, monkeypatch):
    monkeypatch.chdir(store["path"])  # the store's folder is the working directory: nothing new
    before = contents(store["path"])
    cfg = compose_cfg(["env=pendulum", *TINY, *store["overrides"], *overrides])
    with pytest.raises(ConfigError) as error:
        train(cfg)
    message = str(error.value)
    assert "\n" not in message
    for word in expected:
        assert word in message
    if not overrides[0].startswith("tracking.uri"):
        assert all_runs(store["client"]) == []
    assert contents(store["path"]) == before


# Every case is refused in-process above; these prove the command line's part: one line, exit 2,
# and no outputs/ folder (a plain bad value, refused before Hydra starts; resume=$RUN_ID with the
# variable unset, which only a shell makes; a run id the store lacks, refused in the job).
@pytest.mark.parametrize("case", [0, 14, 17], ids=lambda i: " ".join(CASES[i][0]))
def test_cli_prints_one_line_and_exits_2(store, case):
    overrides, expected = CASES[case]
    before = contents(store["path"])
    result = run_cli(["env=pendulum", *TINY, *store["overrides"], *overrides], cwd=store["path"])
    error = one_line_error(result)
    assert all(word in error for word in expected)
    assert all_runs(store["client"]) == []
    assert contents(store["path"]) == before


@pytest.mark.parametrize(
    "module,key", [("walkers.train", "resume"), ("walkers.evaluate", "run_id")]
)
def test_a_run_id_on_a_store_that_does_not_exist_creates_no_store(tmp_path, module, key):
    """Connecting to a sqlite file creates it: a command that reads a run refuses first."""
    result = run_cli([f"{key}=0123456789abcdef"], cwd=tmp_path, module=module)
    error = one_line_error(result)
    assert f"{key}='0123456789abcdef' is not a run in tracking.uri='sqlite:///mlflow.db'" in error
    assert "mlflow.db does not exist" in error
    assert list(tmp_path.iterdir()) == []


COMPOSITION_CASES = [
    # Hydra's own errors (unknown option or key), as one line before Hydra runs
    (["algo=foo"], ["algo='foo'", "reinforce, sac, td3"]),
    (["env=walker3d"], ["env='walker3d'", "walker2d"]),
    (["totl_steps=5"], ["totl_steps=5", "no key 'totl_steps'", "did you mean 'total_steps'?"]),
    (["evn=hopper"], ["evn=hopper", "no key 'evn'", "did you mean 'env'?"]),
    (["algo.lrr=1e-3"], ["algo.lrr=1e-3", "no key 'algo.lrr'", "did you mean 'algo.lr'?"]),
    (["algo=td33"], ["algo='td33'", "did you mean 'td3'?", "reinforce, sac, td3"]),
    (["algo.momentum=0.9"], ["algo.momentum=0.9", "no key"]),
    (["-m", "algo=td3,foo", "seed=0,1"], ["algo='foo'"]),
    (["-m", "sweeps=nope"], ["sweeps='nope'", "td3_walker2d"]),
    (["hydra/launcher=nope"], ["hydra/launcher='nope'", "joblib"]),
    # an interpolation that names no key, in any job of a multirun
    (["tracking.run_name=x-${env.nme}"], ["tracking.run_name=x-${env.nme}", "'env.nme' not found"]),
    (["-m", "env=hopper,pendulum", "job_key=b/${env.name}"], ["job_key=b/${env.name}", "env.name"]),
]


@pytest.mark.parametrize("args,expected", COMPOSITION_CASES, ids=lambda c: " ".join(c))
def test_composition_errors_are_one_line(capsys, args, expected):
    with pytest.raises(SystemExit) as exit_:
        exit_on_bad_overrides("train", args)
    assert exit_.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("error: ") and all(word in line for word in expected), line


def test_good_command_lines_pass_the_composition_check():
    exit_on_bad_overrides("train", ["--cfg", "job", "algo=ddpg", "env=pendulum"])
    exit_on_bad_overrides("train", ["-m", "algo=td3,ddpg", "seed=range(3)", "sweeps=td3_walker2d"])
    exit_on_bad_overrides("compare", ["env=pendulum", "algos=[td3,reinforce]"])


def test_cli_unknown_algorithm(store):
    error = one_line_error(run_cli(["algo=foo", *store["overrides"]], cwd=store["path"]))
    assert "algo='foo'" in error and "reinforce, sac, td3" in error


def test_a_variable_the_job_reads_from_its_environment_is_named_when_missing(store):
    """A Ray node started before the study's variable was exported: one line, nothing created."""
    args = ["trial.storage=${oc.env:WALKERS_TEST_NOT_EXPORTED}", *TINY, *store["overrides"]]
    line = one_line_error(run_cli(args, cwd=store["path"]))
    assert line.startswith("error: WALKERS_TEST_NOT_EXPORTED is not set on ")
    assert "before `ray start`" in line
    assert all_runs(store["client"]) == []


@pytest.mark.parametrize("multirun", [[], ["-m", "seed=0,1"]], ids=["run", "multirun"])
def test_a_password_in_the_tracking_uri_is_refused_before_hydra_writes_it(tmp_path, multirun):
    """Refused in the job, the URL had already reached Hydra's .hydra/ files and launch log."""
    uri = "tracking.uri=postgresql://walker:hunter2@127.0.0.1:1/mlflow"
    result = run_cli([*multirun, uri], cwd=tmp_path)
    assert "tracking.uri='postgresql://walker:***@127.0.0.1:1/mlflow' carries a password" in (
        one_line_error(result)
    )
    assert "hunter2" not in result.stdout + result.stderr
    assert list(tmp_path.iterdir()) == []  # no outputs/ or multirun/ holding it
