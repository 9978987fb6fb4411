"""Replaying trained policies: returns, videos, logging to the run; gifs during training."""

from __future__ import annotations

import json

import imageio.v3 as iio
import pytest
from PIL import Image, ImageSequence

from tests.conftest import TINY, all_runs, compose_cfg, new_store, one_line_error, run_cli
from walkers.errors import ConfigError
from walkers.seeding import eval_start_seeds, held_out_start_seeds
from walkers.train import train
from walkers.training.checkpoint_evaluation import evaluate

PENDULUM_STEPS = 200  # Pendulum-v1 episodes always last 200 steps


@pytest.fixture(scope="module")
def trained(tmp_path_factory, _empty_store_file):
    """One tiny TD3 run on Pendulum (gif every 300 steps), in its own store."""
    store = new_store(tmp_path_factory.mktemp("evaluate"), _empty_store_file)
    train(compose_cfg(["algo=td3", "env=pendulum", *TINY, "video_every=300", *store["overrides"]]))
    (run,) = all_runs(store["client"])
    return store, run


def gif_frames_played(path) -> int:
    """Frames a gif plays: its playback time over one frame's duration (Pillow stores a run of
    identical frames as one frame shown that many times longer)."""
    with Image.open(path) as gif:
        durations = [frame.info["duration"] for frame in ImageSequence.Iterator(gif)]
    return round(sum(durations) / min(durations))


def evaluate_cfg(store, run, *overrides):
    return compose_cfg(
        [f"run_id={run.info.run_id}", *store["overrides"], *overrides], config_name="evaluate"
    )


def test_evaluate_reproduces_the_best_evaluation_and_writes_videos(trained, tmp_path):
    store, run = trained
    result = evaluate(
        evaluate_cfg(
            store, run, "checkpoint=best", "episodes=1", "start_states=run", f"out={tmp_path}"
        )
    )
    # best.pt was saved by the evaluation that scored best; replaying it from the run's own
    # evaluation start state must give exactly that score (deterministic policy, same start).
    history = store["client"].get_metric_history(run.info.run_id, "eval/return_mean")
    assert result["return_mean"] == pytest.approx(max(m.value for m in history), abs=1e-4)

    mp4 = next(p for p in result["videos"] if p.suffix == ".mp4")
    frames = iio.imread(mp4)  # decodes with ffmpeg
    assert frames.shape[0] == PENDULUM_STEPS and frames.ndim == 4 and frames.shape[-1] == 3
    assert frames.std() > 0  # not a blank video
    gif = next(p for p in result["videos"] if p.suffix == ".gif")
    # every 2nd frame: 100 frames' worth of playback (Pillow merges identical neighbours into
    # one frame shown longer, e.g. a pendulum at rest)
    assert gif_frames_played(gif) == PENDULUM_STEPS // 2

    logged = {a.path for a in store["client"].list_artifacts(run.info.run_id, "evaluations")}
    assert {f"evaluations/{p.name}" for p in result["videos"]} <= logged
    saved = json.loads(mp4.with_suffix(".json").read_text())
    assert saved["returns"] == result["returns"]
    status = store["client"].get_run(run.info.run_id).info.status
    assert status == "FINISHED"  # logging an evaluation leaves the run as it was


def test_evaluate_defaults_to_start_states_the_run_never_evaluated_on(trained, tmp_path):
    """best.pt was chosen on the run's evaluation start states: its score there is flattered, so
    by default walkers.evaluate plays a held-out seed stream, and says so."""
    store, run = trained
    seed = int(run.data.params["seed"])
    held_out = set(held_out_start_seeds(seed, 5))
    assert not held_out & set(eval_start_seeds(seed, 5))
    common = ("checkpoint=best", "episodes=2", "video=false", f"out={tmp_path}")
    fresh = evaluate(evaluate_cfg(store, run, *common))
    own = evaluate(evaluate_cfg(store, run, *common, "start_states=run"))
    assert fresh["start_states"] == "held_out" and own["start_states"] == "run"
    assert fresh["returns"] != own["returns"]  # other start states, other (continuous) returns
    result = run_cli(
        [f"run_id={run.info.run_id}", "start_states=train", *store["overrides"]],
        cwd=store["path"],
        module="walkers.evaluate",
    )
    error = one_line_error(result)
    assert "start_states='train'" in error and "held_out, run" in error


def test_evaluate_a_checkpoint_file_without_the_run(trained, tmp_path):
    store, run = trained
    path = store["client"].download_artifacts(run.info.run_id, "checkpoints/last.pt", str(tmp_path))
    cfg = compose_cfg(
        [f"checkpoint={path}", "episodes=3", "video=false", *store["overrides"]],
        config_name="evaluate",
    )
    first, again = evaluate(cfg), evaluate(cfg)
    assert len(first["returns"]) == 3 and first["videos"] == []
    assert first["returns"] == again["returns"]  # deterministic episodes, seeded starts


def test_training_logs_gifs_every_video_every_steps(trained):
    store, run = trained
    gifs = [a.path for a in store["client"].list_artifacts(run.info.run_id, "videos")]
    assert gifs == ["videos/step_00000300.gif", "videos/step_00000600.gif"]


def test_evaluate_bad_checkpoint_is_one_line(trained):
    """In-process: the start_states refusal above proves the command line's part."""
    store, run = trained
    with pytest.raises(ConfigError) as refused:
        evaluate(evaluate_cfg(store, run, "checkpoint=newest"))
    error = str(refused.value)
    assert "checkpoint='newest'" in error and "best, last" in error and "\n" not in error
