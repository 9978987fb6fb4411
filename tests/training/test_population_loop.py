"""The population's lockstep step: K envs as one vector env, arrays end to end, the books once
a step, the members' evaluations played together (walkers.training.loops.Lockstep)."""

from __future__ import annotations

import signal

import numpy as np
import pytest
from hydra.utils import get_class

from tests.conftest import (
    TINY,
    all_runs,
    compose_cfg,
    feed_members,
    interrupt_group_once_checkpointed,
    run_cli,
    spawn_cli,
    tiny,
)
from walkers.agents.declarations.schemas import SCHEMAS
from walkers.agents.factory import defaults_for
from walkers.seeding import eval_start_seeds
from walkers.train import train
from walkers.training.bookkeeping import run_episodes, run_population_episodes
from walkers.training.envs import make_env, make_vector_env
from walkers.training.loops import Lockstep, member_scalars, step_vector_env

PENDULUM = {"id": "Pendulum-v1", "max_episode_steps": 200}
#: every algorithm that trains seed populations, from the declarations
POPULATION_ALGOS = [
    name
    for name, schema in SCHEMAS.items()
    if get_class(schema.AGENT).trains_populations and not get_class(schema.AGENT).offline
]


def population(algo: str, k: int = 3):
    cls = get_class(SCHEMAS[algo].AGENT)
    small = {"batch_size": 16, "learning_starts": 20, "hidden_sizes": [16, 16]}
    agent = cls(3, [-2.0], [2.0], population=k, seed=4, **defaults_for(cls, **small))
    feed_members(agent, steps=40)
    return agent


@pytest.mark.parametrize("algo", POPULATION_ALGOS)
def test_members_evaluated_together_score_what_each_scores_alone(algo):
    """Member i's episodes played beside the others (one batched forward a step) start where
    its own evaluation starts and return what it returns played alone, to the rounding of a
    batched matmul against a single one (SAC and CrossQ: bitwise on this CPU)."""
    agent, k = population(algo), 3
    seeds = [eval_start_seeds(4 + i, 2) for i in range(k)]
    envs = [make_env(PENDULUM, shaping=False) for _ in range(k)]
    together = run_population_episodes(agent, envs, seeds)
    alone = np.stack([run_episodes(agent.member_policy(i), envs[i], seeds[i]) for i in range(k)])
    assert together.shape == (k, 2) and len(np.unique(together)) == 2 * k
    np.testing.assert_allclose(together, alone, rtol=1e-5)
    for env in envs:
        env.close()


def test_the_lockstep_step_stores_each_members_own_steps():
    """The K envs step as one vector env whose finished episodes reset in the step: each
    member's buffer holds its own env's transitions, a finished episode's own last observation
    as next_obs (not the next episode's first), and the step's rewards and flags."""
    k, agent = 2, population("td3", k=2)
    agent.buffer.pos = agent.buffer.size = 0  # forget feed_members' made-up steps
    envs = make_vector_env(PENDULUM, k, step_info=False)
    obs, info = envs.reset(seed=[7, 8])
    assert info == {}  # only the episode statistics survive, and there are none yet
    lockstep = Lockstep(agent, envs, obs)
    seen = []
    for _ in range(205):  # past Pendulum's time limit: every member's episode ends at 200
        step, _ = lockstep.step()
        seen.append(step)
    ended = seen[199]
    assert list(ended.ended) == [0, 1] and ended.truncated.all()
    assert set(ended.info) == {"final_obs", "_final_obs", "final_info", "_final_info"}
    assert set(ended.info["final_info"]) == {"episode", "_episode"}
    assert [ended.episode_statistics(i)[1] for i in range(k)] == [200, 200]
    rows = agent.buffer
    for t in (0, 150, 199, 204):
        np.testing.assert_allclose(rows.obs[:, t].numpy(), seen[t].obs, rtol=1e-6)
        np.testing.assert_allclose(rows.next_obs[:, t].numpy(), seen[t].own_next_obs, rtol=1e-6)
        np.testing.assert_allclose(rows.reward[:, t].numpy(), seen[t].rewards, rtol=1e-6)
    # the last step of the episode is its own: not the first state of the next one
    assert not np.allclose(seen[199].own_next_obs, seen[199].next_obs)
    np.testing.assert_allclose(seen[200].obs, seen[199].next_obs)
    assert rows.episode_end[:, 199].all() and not rows.episode_end[:, 198].any()
    envs.close()


def test_a_vector_step_without_step_info_keeps_the_true_returns():
    """Cutting a step's info to the episode statistics changes nothing a run reports: the
    returns are the env's own, as a single env records them."""
    envs = make_vector_env(PENDULUM, 2, step_info=False)
    alone = make_env(PENDULUM)
    obs, _ = envs.reset(seed=[3, 4])
    alone.reset(seed=3)
    actions = np.random.default_rng(0).uniform(-2, 2, size=(200, 2, 1)).astype(np.float32)
    for a in actions:
        step = step_vector_env(envs, obs, a)
        _, _, _, truncated, info = alone.step(a[0])
        obs = step.next_obs
    assert truncated and list(step.ended) == [0, 1]
    assert step.episode_statistics(0) == (float(info["episode"]["r"]), 200)
    envs.close()
    alone.close()


def test_member_scalars_are_each_members_column():
    import torch

    losses = {
        "loss/critic": torch.tensor([1.0, 2.0, 3.0]),
        "health/skipped": torch.tensor([0, 1, 0]),
    }
    assert member_scalars(losses, 3) == [
        {"loss/critic": 1.0, "health/skipped": 0.0},
        {"loss/critic": 2.0, "health/skipped": 1.0},
        {"loss/critic": 3.0, "health/skipped": 0.0},
    ]
    assert member_scalars({}, 2) == [{}, {}]


def test_members_envs_in_worker_processes_train_and_resume_as_in_this_process(store):
    """``vector_env=async`` steps the members' envs in worker processes (AsyncVectorEnv): the
    same envs, so the same runs, metric for metric; and a resume restores each member's env
    RNG through its worker as through the env in this process."""
    client = store["client"]
    common = ["algo=td3", "env=pendulum", "population=2", *TINY, *tiny("td3")]

    def population_runs(vector_env: str) -> list[str]:
        name = f"tracking.experiment=envs_{vector_env}"
        train(
            compose_cfg(
                [*common, "total_steps=300", f"vector_env={vector_env}", name, *store["overrides"]]
            )
        )
        runs = [r for r in all_runs(client) if r.data.params["vector_env"] == vector_env]
        ids = [r.info.run_id for r in sorted(runs, key=lambda r: r.data.params["seed"])]
        given = ["total_steps=600", f"vector_env={vector_env}"]
        train(compose_cfg([f"resume=[{','.join(ids)}]", *given, *store["overrides"]]), given)
        return ids

    def histories(run_id: str) -> dict[str, list[tuple[int, float]]]:
        metrics = client.get_run(run_id).data.metrics
        wanted = [m for m in metrics if m.startswith(("train/", "eval/", "loss/"))]
        return {
            m: [(h.step, h.value) for h in client.get_metric_history(run_id, m)] for m in wanted
        }

    in_process, in_workers = population_runs("sync"), population_runs("async")
    for mine, theirs in zip(in_workers, in_process, strict=True):
        assert client.get_run(mine).info.status == "FINISHED"
        got, expected = histories(mine), histories(theirs)
        assert got == expected and [s for s, _ in got["eval/return_mean"]] == [300, 600]


@pytest.mark.faults  # `make test-faults`: Ctrl-C to a whole process group
def test_ctrl_c_to_the_process_group_leaves_the_env_workers_to_the_run(store):
    """A terminal's Ctrl-C reaches every process of its group, the env workers of
    ``vector_env=async`` too: they leave it to the training process, which ends its step, writes
    each member's last checkpoint (their env RNGs read through the workers) and ends KILLED;
    the resume it prints continues both members to their budget."""
    args = ["algo=td3", "env=pendulum", "population=2", "vector_env=async", *TINY,
            "total_steps=3000", *tiny("td3"), *store["overrides"]]  # fmt: skip
    proc = spawn_cli(args, cwd=store["path"], new_session=True)
    stderr = interrupt_group_once_checkpointed(proc, store["path"], "last.pt")
    assert proc.returncode == 130, stderr[-3000:]
    runs = all_runs(store["client"])
    assert len(runs) == 2 and {r.info.status for r in runs} == {"KILLED"}
    ids = ",".join(r.info.run_id for r in sorted(runs, key=lambda r: r.data.params["seed"]))
    again = run_cli([f"resume=[{ids}]", *store["overrides"]], cwd=store["path"])
    assert again.returncode == 0, again.stderr[-3000:]
    assert {r.info.status for r in all_runs(store["client"])} == {"FINISHED"}


def test_env_workers_leave_the_training_process_its_signal_handlers():
    """Gymnasium builds one env in the training process to read the spaces from: the workers'
    ignoring of Ctrl-C and SIGTERM must not reach the training process (a SIGTERM it ignored
    would leave the run training, and every process it starts would ignore it too). That the
    workers ignore them is the test above."""
    were = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    # the handlers a training process has (a pytest-xdist worker ignores SIGINT itself)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        envs = make_vector_env(compose_cfg(["env=pendulum"]).env, 2, vector_env="async")
        try:
            now = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
            assert now == (signal.default_int_handler, signal.SIG_DFL)
        finally:
            envs.close()
    finally:
        signal.signal(signal.SIGINT, were[0])
        signal.signal(signal.SIGTERM, were[1])
