"""What the study and bundle tests share: a tiny study's command line, its runs, and the export
and import commands run as a user runs them."""

from __future__ import annotations

import pytest
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.plugins import Plugins
from hydra.types import HydraContext, RunMode

from tests.conftest import all_runs, run_cli
from walkers import CONF_DIR


#: Two arms that cannot be confused: the same untrained REINFORCE, one with episodes half as
#: long on Pendulum (about half the negative return).
def arms(mapping: str) -> list[str]:
    """Command-line overrides that replace the study file's arms (a user edits the file)."""
    return ["~hydra.sweeper.arms", f"+hydra.sweeper.arms={mapping}"]


OBVIOUS = arms("{short:'algo=reinforce env.max_episode_steps=100',long:'algo=reinforce'}")
#: The same difference between two TD3 arms (TD3 trains seed populations), learning in 400 steps.
_TD3 = "algo=td3 algo.learning_starts=100 algo.batch_size=32 algo.hidden_sizes=[32,32]"
OBVIOUS_TD3 = arms(f"{{short:'{_TD3} env.max_episode_steps=100',long:'{_TD3}'}}")
TINY_JOBS = [
    "total_steps=400",
    "eval_every=200",
    "eval_episodes=2",
    "checkpoint_every=200",
    "hydra.sweeper.envs=[pendulum]",
    "hydra.sweeper.seeds={min:5,max:7,per_round:1}",
]


def study(store, *overrides: str, name: str = "t") -> list[str]:
    return [
        "-m",
        "ab=tiny",
        f"hydra.sweeper.name={name}",
        *TINY_JOBS,
        *overrides,
        *store["overrides"],
    ]


def job_runs(store) -> list:
    return [r for r in all_runs(store["client"]) if "walkers.job_key" in r.data.tags]


def study_run(store):
    (run,) = [r for r in all_runs(store["client"]) if r.data.tags.get("walkers.kind") == "ab"]
    return run


def export(store, *args: str):
    return run_cli(
        ["tracking.experiment=ab_tiny", *args, f"tracking.uri={store['uri']}"],
        cwd=store["path"],
        module="walkers.export",
    )


def ingest(store, bundle, *args: str):
    return run_cli(
        [f"bundle={bundle}", *args, f"tracking.uri={store['uri']}"],
        cwd=store["path"],
        module="walkers.ingest",
    )


def refusal_in_process(store, capsys, *overrides: str) -> str:
    """The one line a study's sweeper refuses ``overrides`` with, its checks run in this process
    as Hydra's multirun hands them the composed config (the command line's own part, exit 2 and
    nothing written, is proven by test_ab's never-deciding study)."""
    args = study(store, *overrides)[1:]  # what follows -m
    with initialize_config_dir(config_dir=str(CONF_DIR)):
        loader = GlobalHydra.instance().config_loader()
        config = loader.load_configuration("train", args, run_mode=RunMode.MULTIRUN)
        HydraConfig.instance().set_config(config)
        context = HydraContext(config_loader=loader, callbacks=None)  # no job is launched
        sweeper = Plugins.instance().instantiate_sweeper(
            config=config, hydra_context=context, task_function=None
        )
        capsys.readouterr()
        try:
            with pytest.raises(SystemExit) as ended:
                sweeper.sweep(arguments=list(config.hydra.overrides.task))
        finally:
            HydraConfig.instance().cfg = None  # as Hydra leaves no run behind: later tests see none
    lines = capsys.readouterr().err.strip().splitlines()
    assert ended.value.code == 2 and len(lines) == 1, lines
    return lines[0]
