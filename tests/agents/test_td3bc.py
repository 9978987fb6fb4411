"""TD3+BC (algo=td3bc): its actor loss against a hand computation, the dataset's state
normalization in the buffer and in acting, and a tiny chain end to end: TD3 on Pendulum -> a
dataset of it and a random policy -> TD3+BC on it (gradient steps) -> a report beside TD3 -> a
resume that goes on where it stopped.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from tests.conftest import (
    TINY,
    all_runs,
    compose_cfg,
    metric_steps,
    new_store,
    one_line_error,
    pendulum_report,
    run_cli,
    run_cli_signalled_inside_an_update,
)
from walkers.agents.factory import defaults_for
from walkers.agents.td3 import TD3
from walkers.agents.td3bc import TD3BC
from walkers.analysis.comparison import compare
from walkers.analysis.suite_report import compare_datasets, compare_suite
from walkers.data import datasets
from walkers.data.datasets import OfflineData
from walkers.data.episodes import Episode
from walkers.data.replay import Batch
from walkers.errors import ConfigError
from walkers.tracking.names import total_steps_of
from walkers.train import train
from walkers.training.checkpoint_evaluation import evaluate
from walkers.training.dataset_recording import collect
from walkers.training.envs import make_env
from walkers.training.run import agent_from_checkpoint, read_checkpoint
from walkers.training.settings import validate

SMALL = {"hidden_sizes": [16, 16], "batch_size": 32}
MEAN, STD = np.array([5.0, -1.0, 0.0]), np.array([1.0, 2.0, 3.0])


def _dataset(episodes: int = 3, steps: int = 50) -> OfflineData:
    """Pendulum-shaped episodes (3 state dims, 1 action in [-2, 2]) of known state statistics;
    the first one ends in a termination, the others are cut by the time limit."""
    rng = np.random.default_rng(0)
    recorded = []
    for i in range(episodes):
        last = np.r_[np.zeros(steps - 1, bool), True]
        recorded.append(
            Episode(
                observations=(MEAN + STD * rng.normal(size=(steps + 1, 3))).astype(np.float32),
                actions=rng.uniform(-2, 2, (steps, 1)).astype(np.float32),
                rewards=rng.normal(size=steps),
                terminations=last & (i == 0),
                truncations=last & (i != 0),
            )
        )
    return OfflineData("test/pendulum/synthetic-v0", "Pendulum-v1", recorded, None, None)


def _agent(dataset: OfflineData | None, **overrides) -> TD3BC:
    return TD3BC(3, [-2.0], [2.0], dataset=dataset, **defaults_for(TD3BC, **SMALL, **overrides))


# --- the loss ---------------------------------------------------------------------------------
def test_the_actor_loss_is_lambda_q_plus_behaviour_cloning_by_hand():
    """Q_1(s, pi(s)) = [1, -3], pi(s) = [0.5, 0], a = [0, 1]: lambda = 2.5 / mean |Q| = 1.25,
    -lambda mean Q = 1.25, BC = (0.25 + 1) / 2 = 0.625; lambda is a constant (no gradient)."""
    agent = _agent(None)
    q = torch.tensor([[1.0, -3.0]], requires_grad=True)
    pi = torch.tensor([[[0.5], [0.0]]], requires_grad=True)
    agent.actor = lambda obs: pi
    agent.q1 = lambda obs, action: q if action is pi else None
    action = torch.tensor([[[0.0], [1.0]]])
    b = Batch(
        torch.zeros(1, 2, 3), action, torch.zeros(1, 2), torch.zeros(1, 2, 3), torch.zeros(1, 2)
    )
    loss = agent.actor_loss(b)
    assert loss.shape == (1,) and loss.item() == pytest.approx(1.25 + 0.625)
    loss.sum().backward()
    assert q.grad.tolist() == [[-1.25 / 2, -1.25 / 2]]  # -lambda / N: lambda held constant
    assert pi.grad.flatten().tolist() == pytest.approx([2 * 0.5 / 2, 2 * -1.0 / 2])


def test_the_actor_loss_is_td3s_scaled_plus_bc_and_the_critics_are_td3s():
    """On the real networks: lambda times TD3's actor loss (-mean Q_1) plus the mean squared
    error to the dataset's actions; the critics' update and target are TD3's own methods."""
    agent = _agent(_dataset())
    b = agent.sample()
    pi = agent.actor(b.obs)
    q = agent.q1(b.obs, pi)
    lmbda = 2.5 / q.abs().mean(dim=-1)
    bc = ((pi - b.action) ** 2).mean(dim=(1, 2))
    expected = lmbda * TD3.actor_loss(agent, b) + bc
    torch.testing.assert_close(agent.actor_loss(b), expected)
    assert TD3BC.critic_loss is TD3.critic_loss and TD3BC.update is TD3.update
    assert (agent.policy_noise, agent.noise_clip, agent.policy_delay, agent.tau) == (
        0.2,
        0.5,
        2,
        0.005,
    )
    metrics = [agent.update() for _ in range(4)]  # the actor every second update, as TD3's
    assert ["loss/actor" in m for m in metrics] == [False, True, False, True]


# --- the dataset's state normalization ----------------------------------------------------------
def test_compiled_td3bc_follows_the_eager_one():
    """``compile=true`` on the CPU compiles TD3's whole update, TD3+BC's actor loss in it: six
    updates (the delayed step three times) come out as the eager ones, to float rounding."""
    eager, compiled = _agent(_dataset()), _agent(_dataset(), compile=True)
    for _ in range(6):
        torch.manual_seed(0)
        expected = eager.update()
        torch.manual_seed(0)
        got = compiled.update()
        assert set(got) == set(expected)
        for key, value in expected.items():
            torch.testing.assert_close(got[key], value, msg=key)
    for name in ("actor", "critic"):
        mine = getattr(compiled, name).state_dict()
        for key, value in getattr(eager, name).state_dict().items():
            torch.testing.assert_close(mine[key], value, msg=f"{name}.{key}")


def test_states_are_normalized_with_the_datasets_mean_and_std_in_the_buffer_and_in_acting():
    data = _dataset()
    agent = _agent(data)
    states = np.concatenate([e.observations[:-1] for e in data.episodes])  # s, not s'
    np.testing.assert_allclose(agent.obs_mean, states.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(agent.obs_std, states.std(axis=0) + 1e-3, rtol=1e-6)
    n = data.steps
    assert len(agent.buffer) == n == agent.buffer.capacity
    buffer = {k: getattr(agent.buffer, k)[0, :n].numpy() for k in ("obs", "next_obs", "terminated")}
    normalized = (states - agent.obs_mean) / agent.obs_std
    np.testing.assert_allclose(buffer["obs"], normalized, rtol=1e-5, atol=1e-6)
    next_states = np.concatenate([e.observations[1:] for e in data.episodes])
    np.testing.assert_allclose(
        buffer["next_obs"], (next_states - agent.obs_mean) / agent.obs_std, rtol=1e-5, atol=1e-6
    )
    assert buffer["terminated"].sum() == 1 and buffer["terminated"][49] == 1  # not truncations
    np.testing.assert_array_equal(
        agent.buffer.action[0, :n].numpy(), np.concatenate([e.actions for e in data.episodes])
    )
    s = data.episodes[1].observations[7]
    with torch.no_grad():
        pi = agent.actor(torch.as_tensor(normalized[57]).view(1, 1, 3))[0, 0].numpy()
    np.testing.assert_allclose(agent.act(s, explore=False), pi, rtol=1e-5)
    np.testing.assert_array_equal(agent.act(s, explore=True), agent.act(s, explore=False))

    raw = _agent(data, normalize_states=False)
    np.testing.assert_array_equal(raw.buffer.obs[0, :n].numpy(), states)


def test_a_checkpoint_acts_without_the_dataset_and_resumes_with_it():
    """The normalization is in the checkpoint, the dataset is not (it is reloaded by name)."""
    data = _dataset()
    agent = _agent(data)
    for _ in range(3):
        agent.update()
    state = agent.state_dict(with_buffer=True)
    assert {"obs_mean", "obs_std"} <= set(state) and "data" not in state["buffer"]
    acting = _agent(None)  # walkers.evaluate, walkers.collect: no dataset
    acting.load_state_dict(state)
    s = data.episodes[2].observations[3]
    np.testing.assert_array_equal(acting.act(s, explore=False), agent.act(s, explore=False))
    resumed = _agent(data)
    resumed.load_state_dict(state)
    assert len(resumed.buffer) == data.steps and resumed.num_updates == 3
    assert torch.equal(resumed.sample().obs, agent.sample().obs)  # the sampler goes on
    assert "loss/actor" in resumed.update()  # update 4: the delayed step


# --- a tiny chain end to end --------------------------------------------------------------------
TD3_STEPS = 400  # env steps: two Pendulum episodes
TD3_RUN = [
    *TINY,
    f"total_steps={TD3_STEPS}",
    "eval_every=200",
    "checkpoint_every=200",
    "algo.learning_starts=100",
    "algo.batch_size=32",
    "algo.hidden_sizes=[16,16]",
]
DATASET = "walkers/pendulum/tiny-td3bc-v0"
STEPS = 300  # gradient steps
TD3BC_RUN = [
    "algo=td3bc",
    "env=pendulum",
    f"dataset={DATASET}",
    f"total_steps={STEPS}",
    "eval_every=150",
    "checkpoint_every=150",
    "log_every=50",
    "eval_episodes=1",
    "algo.hidden_sizes=[32,32]",
    "algo.batch_size=64",
    "progress=false",
]


@pytest.fixture(scope="module")
def chain(tmp_path_factory, _empty_store_file):
    """A tiny TD3 run, a dataset of it and a random policy, a TD3+BC run on the dataset."""
    store = new_store(tmp_path_factory.mktemp("td3bc"), _empty_store_file)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(store["path"] / "minari"))
        train(compose_cfg(["algo=td3", "env=pendulum", *TD3_RUN, *store["overrides"]]))
        (td3,) = all_runs(store["client"])
        collect(
            compose_cfg(
                [
                    f"run_id=[random,{td3.info.run_id}]",
                    "env=pendulum",
                    "episodes=2",
                    "random_episodes=2",
                    f"dataset={DATASET}",
                    "log_to_mlflow=false",
                    *store["overrides"],
                ],
                config_name="collect",
            )
        )
        train(compose_cfg([*TD3BC_RUN, *store["overrides"]]))
        (run,) = [r for r in all_runs(store["client"]) if r.data.tags.get("algo") == "td3bc"]
        yield {**store, "run": run}


def test_a_td3bc_run_counts_gradient_steps_and_reports_a_normalized_score(chain):
    run, client = chain["run"], chain["client"]
    assert run.info.status == "FINISHED"
    assert (
        run.data.tags["walkers.x_axis"] == "gradient_steps" and run.data.tags["dataset"] == DATASET
    )
    assert run.data.params["dataset_stats.steps"] == str(4 * 200)
    assert metric_steps(client, run.info.run_id, "eval/return_mean") == [150, STEPS]
    assert metric_steps(client, run.info.run_id, "loss/critic") == [50, 100, 150, 200, 250, 300]
    assert {"final/normalized_score", "eval/normalized_score", "loss/actor"} <= set(
        run.data.metrics
    )
    assert "perf/gradient_steps_per_s" in run.data.metrics
    env = make_env({"id": "Pendulum-v1", "max_episode_steps": 200}, shaping=False)
    state = read_checkpoint(
        client.download_artifacts(run.info.run_id, "checkpoints/last.pt", str(chain["path"]))
    )
    _, agent = agent_from_checkpoint(state, env, "cpu")  # no dataset: the stats come with it
    env.close()
    assert isinstance(agent, TD3BC) and agent.obs_std.shape == (3,) and agent.obs_std.min() > 0
    replay = evaluate(
        compose_cfg(
            [f"run_id={run.info.run_id}", "episodes=1", "video=false", *chain["overrides"]],
            config_name="evaluate",
        )
    )
    assert np.isfinite(replay["return_mean"])


def test_report_puts_td3bc_beside_td3(chain, tmp_path):
    comparison, out, _ = pendulum_report(chain["overrides"], ["td3", "td3bc"], tmp_path)
    td3bc = next(r for r in comparison.algos if r.algo == "td3bc")
    assert td3bc.x_axis == "gradient_steps" and td3bc.dataset == DATASET
    assert comparison.budgets == {"env_steps": TD3_STEPS, "gradient_steps": STEPS}
    report = (out / "report.md").read_text()
    assert f"td3bc (offline, {DATASET})" in report


def test_a_td3bc_run_resumes_where_it_stopped(chain):
    """100 more gradient steps: the same run goes on from its dataset (reloaded, not emptied),
    no step logged twice."""
    run_id, client = chain["run"].info.run_id, chain["client"]
    more = STEPS + 100
    train(
        compose_cfg([f"resume={run_id}", f"total_steps={more}", *chain["overrides"]]),
        overrides=[f"total_steps={more}"],
    )
    steps = metric_steps(client, run_id, "loss/critic")
    assert steps == sorted(set(steps)) and steps[-1] == more
    assert client.get_run(run_id).info.status == "FINISHED"
    assert len([r for r in all_runs(client) if r.data.tags.get("algo") == "td3bc"]) == 1


@pytest.mark.faults  # `make test-faults`: a signal, sent by the run to itself
def test_a_run_stopped_inside_an_update_resumes_into_the_uninterrupted_run(chain, tmp_path):
    """SIGINT between the critic's and the actor's step of update 100 (TD3+BC's 149th Adam step:
    99 critic and 49 actor steps before it): the stop waits for the update to end, the last
    checkpoint holds whole updates (step 100), and the resumed run logs, bit for bit, what the
    uninterrupted run of the same seed logs."""
    store = new_store(tmp_path)
    args = [*TD3BC_RUN, "seed=3", "torch_threads=1", *store["overrides"]]
    env = {"MINARI_DATASETS_PATH": str(chain["path"] / "minari")}
    whole = run_cli([*args, "tracking.experiment=whole"], cwd=tmp_path, env_overrides=env)
    assert whole.returncode == 0, whole.stderr[-2000:]
    cut = run_cli_signalled_inside_an_update(args, tmp_path, 149, env_overrides=env)
    assert cut.returncode == 130, cut.stderr[-2000:]
    assert "stopping (SIGINT): the step under way ends first" in cut.stderr
    client = store["client"]
    (stopped,) = client.search_runs([client.get_experiment_by_name("walkers").experiment_id])
    assert stopped.info.status == "KILLED"
    path = client.download_artifacts(stopped.info.run_id, "checkpoints/last.pt", str(tmp_path))
    assert read_checkpoint(path)["trainer"]["step"] == 100
    resumed = run_cli([f"resume={stopped.info.run_id}", *args], cwd=tmp_path, env_overrides=env)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    (reference,) = client.search_runs([client.get_experiment_by_name("whole").experiment_id])
    for key in ("loss/critic", "loss/actor", "eval/return_mean"):
        curves = [
            [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, key)]
            for run in (reference, stopped)
        ]
        assert curves[0] == curves[1], key


def test_td3bc_bad_input_is_one_line(chain):
    with pytest.raises(ConfigError, match=r"^dataset=None is not allowed: algo=td3bc"):
        validate(compose_cfg(["algo=td3bc", "env=pendulum"]))
    offline = ["algo=td3bc", "env=pendulum", f"dataset={DATASET}"]
    with pytest.raises(
        ConfigError,
        match=r"^population=2 is not allowed with algo=td3bc: only [a-z0-9, ]+ train seed "
        r"populations \(an offline run trains one seed",
    ):
        validate(compose_cfg([*offline, "population=2"]))
    with pytest.raises(ConfigError, match=r"^impl=sb3 is not available for algo=td3bc"):
        validate(compose_cfg([*offline, "impl=sb3"]))
    with pytest.raises(ConfigError, match=r"only offline algorithms \(dt, td3bc\)"):
        validate(compose_cfg(["algo=td3", "dataset=x"]))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(chain["path"] / "minari"))
        with pytest.raises(ConfigError, match=r"recorded on Pendulum-v1, not on env.id='Hopper"):
            train(compose_cfg([*TD3BC_RUN, "env=hopper", *chain["overrides"]]))
        with pytest.raises(ConfigError, match=r"^algo.batch_size=1000 is more than the 800"):
            train(compose_cfg([*TD3BC_RUN, "algo.batch_size=1000", *chain["overrides"]]))
        runs_before = len(all_runs(chain["client"]))
        unknown_family = [f for f in TD3BC_RUN if not f.startswith("dataset=")]
        with pytest.raises(
            ConfigError,
            match=r"^dataset='walkers/pendulum/mediocre' is not a local Minari dataset in .*; "
            rf"local datasets: {DATASET} \(make one with `python -m walkers.collect`",
        ):
            train(
                compose_cfg(
                    [*unknown_family, "dataset=walkers/pendulum/mediocre", *chain["overrides"]]
                )
            )
        assert len(all_runs(chain["client"])) == runs_before  # refused before any run was made


DT_STEPS = 60  # gradient steps: a tiny DT beside TD3+BC's 300
DT_RUN = [
    "algo=dt",
    "env=pendulum",
    f"dataset={DATASET}",
    f"total_steps={DT_STEPS}",
    "eval_every=30",
    "checkpoint_every=30",
    "log_every=30",
    "eval_episodes=1",
    "algo.embed_dim=16",
    "algo.n_layers=1",
    "algo.context_length=4",
    "algo.batch_size=8",
    "algo.warmup_steps=10",
    "progress=false",
]


def test_offline_algorithms_are_compared_each_at_its_own_budget(chain, tmp_path):
    """DT for 60 gradient steps beside TD3+BC for 300, as their papers train each to its own
    budget (TD3+BC 1M, DT 100k): one report, both budgets named, the final returns compared and
    the AUCs (means over different spans) not. One budget for all keeps only the algorithm that
    has it; a budget per algorithm picks each."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(chain["path"] / "minari"))
        train(compose_cfg([*DT_RUN, *chain["overrides"]]))

    def report(*overrides: str):
        return compare(
            compose_cfg(
                [
                    *chain["overrides"],
                    "env=pendulum",
                    "algos=[td3bc,dt]",
                    f"out={tmp_path}",
                    "n_resamples=200",
                    *overrides,
                ],
                config_name="compare",
            )
        )

    # TD3+BC's budget is what its run trained for: 300, or 400 once the resume test above has
    # continued it (its param still says 300)
    steps = int(total_steps_of(chain["client"].get_run(chain["run"].info.run_id)))
    comparison, out, _ = report()
    assert comparison.budgets == {"gradient_steps": {"dt": DT_STEPS, "td3bc": steps}}
    assert [p.quantity for p in comparison.pairs] == ["score"]
    assert {r.algo: r.budget for r in comparison.algos} == {"td3bc": steps, "dt": DT_STEPS}
    assert f"dt {DT_STEPS:,} and td3bc {steps:,} gradient steps" in (out / "report.md").read_text()
    comparison, _, _ = report(f"gradient_steps={{td3bc:{steps},dt:{DT_STEPS}}}")
    assert comparison.budgets == {"gradient_steps": {"dt": DT_STEPS, "td3bc": steps}}
    with pytest.raises(ConfigError, match=r"has no finished Pendulum-v1 runs for dt .*budget"):
        report(f"gradient_steps={steps}")
    with pytest.raises(
        ConfigError,
        match=r"^gradient_steps=\{'dt': -5\} is not allowed: must be null, a positive integer",
    ):
        report("gradient_steps={dt:-5}")


SECOND = "walkers/pendulum/tiny-td3-only-v0"


@pytest.mark.slow  # `make test-slow`: collects a second dataset and trains both offline arms on it
def test_a_suite_of_datasets_aggregates_the_offline_arms_across_them(chain, tmp_path):
    """TD3+BC and DT, 2 seeds each, on two datasets of one env: each dataset's report, then
    the suite's over the offline arms (normalized on each dataset's references, the data's own
    score beside them, DT per target, Holm over 2 pairs-on-datasets), from the CLI. A dataset
    named without its version is found; a typo, a single dataset and envs= beside datasets= are
    one-line errors."""
    experiment = ["tracking.experiment=offline_suite"]
    td3 = next(r for r in all_runs(chain["client"]) if r.data.tags.get("algo") == "td3")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(chain["path"] / "minari"))
        collect(
            compose_cfg(
                [f"run_id={td3.info.run_id}", "episodes=2", "random_episodes=2",
                 f"dataset={SECOND}", "log_to_mlflow=false", *chain["overrides"]],
                config_name="collect",
            )
        )  # fmt: skip
        for dataset, seed in itertools.product((DATASET, SECOND), (0, 1)):
            common = [f"dataset={dataset}", f"seed={seed}", *experiment, *chain["overrides"]]
            train(compose_cfg([*TD3BC_RUN, "total_steps=100", "eval_every=50", *common]))
            train(compose_cfg([*DT_RUN, "algo.target_returns=[-150,-900]", *common]))
    out = tmp_path / "reports"
    args = ["env=pendulum", "algos=[td3bc,dt]", "n_resamples=200", *experiment, *chain["overrides"]]
    suite_cli = [*args, f"out={out}"]
    result = run_cli(
        [*suite_cli, f"datasets=[{DATASET},{SECOND.removesuffix('-v0')}]"],
        cwd=chain["path"],
        module="walkers.compare",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "suite of 2 datasets: the highest normalized IQM is" in result.stdout
    summary = json.loads((out / "datasets" / "summary.json").read_text())
    assert set(summary["aggregates"]) == {"td3bc", "dt"}
    assert set(summary["holm_adjusted"]) == {f"td3bc vs dt on {d}" for d in (DATASET, SECOND)}
    assert summary["budgets"] == {"td3bc": 100, "dt": DT_STEPS}
    hours = summary["cpu_hours"]["dt"]
    assert hours[0] > 0 and hours[1:] == [4, 4]
    for dataset in (DATASET, SECOND):  # references of each dataset: its random and its data
        refs = summary["datasets"][dataset]
        assert refs["own"] == pytest.approx(100.0) and refs["random"] != refs["reference"]
        assert (out / dataset.replace("/", "_") / "report.md").is_file()  # each its own report
    report = (out / "datasets" / "report.md").read_text()
    assert "| the data's own | 100.0 | 100.0 |" in report
    assert "## dt per target return" in report and "| -150 |" in report and "| -900 |" in report
    assert "Budgets: td3bc 100 gradient steps; dt 60 gradient steps." in report
    for name in ("performance_profile.png", "sample_efficiency.png"):
        assert (out / "datasets" / name).stat().st_size > 1000

    typo = [*args, f"out={tmp_path / 'typo'}"]
    line = one_line_error(
        run_cli(
            [*typo, f"datasets=[{DATASET},walkers/pendulum/tiny-td3-onyl]"],
            cwd=chain["path"],
            module="walkers.compare",
        )
    )
    assert line == (
        "error: dataset='walkers/pendulum/tiny-td3-onyl' is not allowed: no finished offline run "
        f"of Pendulum-v1 learned from it; datasets they learned from: {SECOND}, {DATASET}"
    )
    assert not (tmp_path / "typo").exists()  # every dataset is found before anything is written
    for bad, message in [
        (f"datasets=[{DATASET}]", r"^datasets=\[.*\] is not allowed: two or more different"),
        (f"datasets=[{SECOND},{SECOND.removesuffix('-v0')}]",
         rf"^datasets=\[.*\] is not allowed: {SECOND} is named twice$"),
        (f"datasets={DATASET}", r"^datasets='.*' is not allowed: two or more different"),
    ]:  # fmt: skip
        with pytest.raises(ConfigError, match=message):
            compare_datasets(compose_cfg([*typo, bad], config_name="compare"))
    with pytest.raises(ConfigError, match=r"^envs= and datasets= are not allowed together"):
        both = [*suite_cli, "envs=[pendulum,hopper]", f"datasets=[{DATASET},{SECOND}]"]
        compare_suite(compose_cfg(both, config_name="compare"))


REBUILT = "walkers/pendulum/rebuilt-v0"


def test_a_dataset_rebuilt_under_its_name_is_not_compared_with_its_first_build(chain, tmp_path):
    """A dataset's name does not say which data it holds: a rebuild by other runs (or on
    another CPU) keeps it. Seed 0 learns from a first build, seed 1 from a rebuild of other
    episodes under the same name: seed 0 does not resume on the rebuild, and the report refuses
    the two in one line naming both builds and which runs learned from each, and writes
    nothing. Each run records its data's digest; the same data collected again has the same
    one, and seed 0 then resumes."""
    experiment = ["tracking.experiment=rebuilt", *chain["overrides"]]
    client = chain["client"]

    def build(episodes: int) -> str:
        return _random_dataset(REBUILT, episodes, experiment)

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(chain["path"] / "minari"))
        first = build(episodes=2)
        train(compose_cfg([*TD3BC_RUN, f"dataset={REBUILT}", "seed=0", *experiment]))
        (seed0,) = [r for r in all_runs(client) if r.data.tags.get("dataset") == REBUILT]
        second = build(episodes=3)
        more = [f"total_steps={STEPS + 50}"]  # seed 0 goes on to it below: seed 1 trains to it
        train(compose_cfg([*TD3BC_RUN, f"dataset={REBUILT}", "seed=1", *more, *experiment]))
        resumed = [f"resume={seed0.info.run_id}", *more, *experiment]
        with pytest.raises(ConfigError) as refused:  # seed 0 would go on with other data
            train(compose_cfg(resumed), overrides=more)
        assert str(refused.value) == (
            f"resume={seed0.info.run_id} is not allowed: dataset='{REBUILT}' is not the data the "
            f"run learned from (digest {first} then, {second} now): a rebuild under its name; "
            "restore that build, or train a new run"
        )
        assert build(episodes=2) == first  # the data, not its name: the same episodes again
        train(compose_cfg(resumed), overrides=more)  # its own data back: it goes on
    assert metric_steps(client, seed0.info.run_id, "loss/critic")[-1] == STEPS + 50
    runs = [r for r in all_runs(client) if r.data.tags.get("dataset") == REBUILT]
    assert sorted(r.data.params["dataset_stats.digest"] for r in runs) == sorted([first, second])
    out = tmp_path / "report"
    line = one_line_error(
        run_cli(
            ["env=pendulum", "algos=[td3bc]", f"out={out}", *experiment],
            cwd=chain["path"],
            module="walkers.compare",
        )
    )
    assert line == (
        f"error: dataset='{REBUILT}' is not one dataset here: its runs learned from 2 builds of "
        f"it (2 episodes, 400 steps, return {_return_mean(runs, first)}, digest {first}: td3bc 1; "
        f"3 episodes, 600 steps, return {_return_mean(runs, second)}, digest {second}: td3bc 1); "
        "compare the runs of one build (another experiment: walkers.ingest into=..., or "
        "tracking.experiment= for the new runs)"
    )
    assert not out.exists()


def _random_dataset(name: str, episodes: int, overrides: list[str]) -> str:
    """``name`` (re)built of ``episodes`` uniform random Pendulum episodes; its digest."""
    recorded = collect(
        compose_cfg(
            ["run_id=random", "env=pendulum", f"episodes={episodes}", "random_episodes=2",
             f"dataset={name}", "overwrite=true", "log_to_mlflow=false", *overrides],
            config_name="collect",
        )
    )  # fmt: skip
    assert recorded["digest"] == datasets.load_local(name).digest  # as written, as read back
    return recorded["digest"]


def test_a_job_run_again_after_its_dataset_was_rebuilt_starts_anew(chain):
    """A keyed job whose earlier run was cut (KILLED) continues that run when run again, unless
    its dataset was rebuilt since: then the earlier run is superseded (FAILED, tagged why) and a
    new run learns from the new data, where continuing would have mixed two datasets."""
    name = "walkers/pendulum/rekeyed-v0"
    job = [*TD3BC_RUN, f"dataset={name}", "job_key=rekeyed/0", "tracking.experiment=rekeyed"]
    client = chain["client"]
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(chain["path"] / "minari"))
        _random_dataset(name, 2, chain["overrides"])
        train(compose_cfg([*job, *chain["overrides"]]))
        (cut,) = [r for r in all_runs(client) if r.data.tags.get("dataset") == name]
        client.set_terminated(cut.info.run_id, "KILLED")  # as a run whose process was killed
        second = _random_dataset(name, 3, chain["overrides"])
        train(compose_cfg([*job, *chain["overrides"]]))
    cut = client.get_run(cut.info.run_id)
    assert cut.info.status == "FAILED"
    assert "which learned from another build of dataset=" in cut.data.tags["walkers.superseded"]
    (new,) = [
        r
        for r in all_runs(client)
        if r.data.tags.get("dataset") == name and r.info.run_id != cut.info.run_id
    ]
    assert new.info.status == "FINISHED" and new.data.params["dataset_stats.digest"] == second


def _return_mean(runs, digest: str) -> str:
    (run,) = [r for r in runs if r.data.params["dataset_stats.digest"] == digest]
    return run.data.params["dataset_stats.return_mean"]
