"""benchmarks/device_offline.sh, the offline call of a lent GPU, tried on the CPU: DT's and TD3+BC's
seeds on one dataset made here train side by side, the finished ones come home as one bundle per
algorithm, and those bundles ingested into the study's store make the same keyed commands there
train nothing."""

from __future__ import annotations

import pytest

from tests.conftest import all_runs, new_store, run_cli, run_device_script, tiny
from walkers.tracking import bundles

#: End to end in bash: `make test-slow` (CI runs it after `make test`).
pytestmark = pytest.mark.slow

DATASET = "walkers/pendulum/random-v0"
ALGOS = ("dt", "td3bc")
STEPS, EVERY = 40, 20
EXTRA = {algo: " ".join([*tiny(algo), "eval_episodes=1", "log_every=10"]) for algo in ALGOS}


@pytest.fixture
def minari_path(tmp_path):
    """A small dataset of uniform random Pendulum episodes, as `walkers.collect` writes it."""
    path = tmp_path / "datasets"
    made = run_cli(
        [
            "run_id=random",
            "env=pendulum",
            "episodes=4",
            "random_episodes=2",
            f"dataset={DATASET}",
            "log_to_mlflow=false",
        ],
        cwd=tmp_path,
        module="walkers.collect",
        env_overrides={"MINARI_DATASETS_PATH": str(path)},
    )
    assert made.returncode == 0, made.stderr[-2000:]
    return path


def run_script(tmp_path, minari_path, deadline: int = 400, steps: int = STEPS):
    return run_device_script(
        "device_offline.sh",
        tmp_path,
        MINARI_DATASETS_PATH=str(minari_path),
        DATASET=DATASET,
        ENV="pendulum",
        SEEDS="0,1",
        ARMS=" ".join(f"{algo}:{steps}" for algo in ALGOS),
        EVERY=str(EVERY),
        EXPERIMENT="offline_pendulum",
        DEADLINE=str(deadline),
        **{f"EXTRA_{algo.upper()}": EXTRA[algo] for algo in ALGOS},
    )


def test_the_finished_seeds_come_home_and_count_as_done_in_the_studys_store(tmp_path, minari_path):
    done = run_script(tmp_path, minari_path)

    assert done.returncode == 0, done.stdout + done.stderr
    home = tmp_path / "home"
    home.mkdir()
    store = new_store(home)
    for algo in ALGOS:
        name = f"{algo}_walkers_pendulum_random"
        assert f"{name}: bundle in" in done.stdout, done.stdout
        document = bundles.read_bundle(tmp_path / "out" / "bundles" / name)
        keys = sorted(r["tags"]["walkers.job_key"] for r in document["runs"])
        assert keys == [f"offline/{algo}/{DATASET}/0", f"offline/{algo}/{DATASET}/1"]
        assert {r["status"] for r in document["runs"]} == {"FINISHED"}
        ingested = run_cli(
            [f"bundle={tmp_path / 'out' / 'bundles' / name}", f"tracking.uri={store['uri']}"],
            cwd=home,
            module="walkers.ingest",
        )
        assert ingested.returncode == 0, ingested.stderr[-2000:]
    for algo in ALGOS:
        rerun = run_cli(  # the keyed command of docs/offline.md, here, on the study's store
            [
                "-m",
                f"algo={algo}",
                "env=pendulum",
                f"dataset={DATASET}",
                "seed=0,1",
                f"total_steps={STEPS}",
                f"eval_every={EVERY}",
                f"checkpoint_every={EVERY}",
                f"job_key=offline/{algo}/${{dataset}}/${{seed}}",
                "tracking.experiment=offline_pendulum",
                *store["overrides"],
                *EXTRA[algo].split(),
            ],
            cwd=home,
            env_overrides={"MINARI_DATASETS_PATH": str(minari_path)},
        )
        assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert len(all_runs(store["client"])) == 4  # the imported runs, nothing trained again
    runs = all_runs(store["client"])  # both arms learned from the one dataset carried there
    assert len({r.data.params["dataset_stats.digest"] for r in runs}) == 1


def test_a_seed_stopped_at_the_deadline_stays_on_the_machine(tmp_path, minari_path):
    # seeds far longer than the deadline, which lands in their training (or, on a slow machine,
    # in their start)
    done = run_script(tmp_path, minari_path, deadline=15, steps=1_000_000)

    assert done.returncode == 0, done.stdout + done.stderr
    assert "stopped at the deadline" in done.stdout
    for algo in ALGOS:
        assert f"{algo}_walkers_pendulum_random: nothing finished" in done.stdout
        assert not (tmp_path / "out" / "bundles" / f"{algo}_walkers_pendulum_random").exists()


def test_an_algorithm_named_twice_is_one_line_before_anything_runs(tmp_path, minari_path):
    done = run_device_script("device_offline.sh", tmp_path, ARMS="dt:40 td3bc:40 dt:80")
    assert done.returncode == 2
    assert (
        done.stderr.strip()
        == 'error: ARMS="dt:40 td3bc:40 dt:80" is not allowed: dt is named twice'
    )
    assert not (tmp_path / "out").exists()
