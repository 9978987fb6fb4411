"""``python -m walkers.evaluate``: replay a trained policy, print its return, record a video.

    python -m walkers.evaluate run_id=<id> checkpoint=best episodes=10 video=true out=<dir>
    python -m walkers.evaluate checkpoint=path/to/best.pt render=human

The checkpoint carries the run's config, so the env and the agent are rebuilt exactly as they
were trained. Episodes are deterministic (``explore=False``). By default they start from
held-out start states, a seed stream the run never evaluated on: ``best.pt`` is the checkpoint
whose periodic evaluation scored highest, so its score on those same start states is biased up
(``start_states=run`` replays them, e.g. to reproduce a logged ``eval/return_mean``).
Rendering is headless (``rgb_array``, MuJoCo through EGL) unless ``render=human``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import DictConfig

from walkers.errors import ConfigError
from walkers.seeding import eval_start_seeds, held_out_start_seeds
from walkers.tracking.client import connect, download_checkpoint, require_run
from walkers.training.bookkeeping import record_episodes
from walkers.training.envs import make_env
from walkers.training.run import Checkpoint, RunFolder, TrainingRun, agent_from_checkpoint
from walkers.training.video import write_videos

log = logging.getLogger("walkers")

NAMED_CHECKPOINTS = ("best", "last")
START_STATES = {"held_out": held_out_start_seeds, "run": eval_start_seeds}
RENDER_MODES = ("rgb_array", "human")


def _check(cfg: DictConfig) -> None:
    if cfg.start_states not in START_STATES:
        raise ConfigError(
            f"start_states={cfg.start_states!r} is not allowed: must be one of "
            + ", ".join(START_STATES)
        )
    if cfg.render not in RENDER_MODES:
        raise ConfigError(f"render={cfg.render!r} is not allowed: must be one of rgb_array, human")
    for key in ("episodes", "video_episodes"):
        if not (isinstance(cfg[key], int) and cfg[key] > 0):
            raise ConfigError(f"{key}={cfg[key]!r} is not allowed: must be an integer > 0")
    if cfg.checkpoint in NAMED_CHECKPOINTS and not cfg.run_id:
        raise ConfigError(
            f"checkpoint={cfg.checkpoint} needs run_id=<MLflow run id>; "
            "or pass checkpoint=<path to a .pt file>"
        )


def fetch_checkpoint(cfg: DictConfig, client) -> Path:
    """The local path of the checkpoint ``cfg`` names (downloaded from the run if named)."""
    if cfg.checkpoint not in NAMED_CHECKPOINTS:
        path = Path(cfg.checkpoint)
        if not path.is_file():
            raise ConfigError(
                f"checkpoint={cfg.checkpoint!r} is not allowed: must be best, last "
                "or the path of an existing .pt file"
            )
        return path
    folder = RunFolder.of(cfg.work_dir, cfg.run_id)
    return download_checkpoint(client, cfg.run_id, f"{cfg.checkpoint}.pt", folder.download)


def evaluate(cfg: DictConfig) -> dict:
    """Replay the policy; returns ``{"returns": [...], "videos": [paths]}``."""

    _check(cfg)
    client = None
    if cfg.run_id:
        client = connect(cfg.tracking.uri, looking_for=f"run_id={cfg.run_id!r}")
        require_run(client, cfg.run_id, cfg.tracking.uri)
    checkpoint = Checkpoint.read(fetch_checkpoint(cfg, client))
    env = make_env(checkpoint.config["env"], shaping=False, render_mode=cfg.render)
    try:
        run_cfg, agent = agent_from_checkpoint(checkpoint, env, cfg.device)
        if cfg.target_return is not None:
            if not agent.return_conditioned:
                raise ConfigError(
                    f"target_return={cfg.target_return!r} is not allowed: the run's algorithm "
                    f"({run_cfg.algo.name}) is not return-conditioned (only dt is)"
                )
            agent.target_return = float(cfg.target_return)
        seed = cfg.seed if cfg.seed is not None else run_cfg.seed
        record = cfg.video and cfg.render == "rgb_array"
        returns, frames, fps = record_episodes(
            agent,
            env,
            START_STATES[cfg.start_states](seed, cfg.episodes),
            render_episodes=cfg.video_episodes if record else 0,
        )
    finally:
        env.close()
    name = cfg.run_id or Path(cfg.checkpoint).stem
    out = Path(cfg.out) if cfg.out else Path(cfg.work_dir) / "evaluations" / name
    stem = out / f"{run_cfg.algo.name}-{run_cfg.env.id}-{Path(str(cfg.checkpoint)).stem}"
    videos = write_videos(frames, stem, fps) if frames else []
    summary = {
        "checkpoint": str(cfg.checkpoint),
        "episodes": cfg.episodes,
        "seed": seed,
        "start_states": cfg.start_states,
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "returns": returns.tolist(),
    }
    out.mkdir(parents=True, exist_ok=True)
    summary_file = stem.with_suffix(".json")
    summary_file.write_text(json.dumps(summary, indent=2))
    if client is not None and cfg.log_to_run:
        run = TrainingRun.attach(client, cfg.work_dir, cfg.run_id)
        for path in [*videos, summary_file]:
            run.upload(path, "evaluations")
    return {**summary, "videos": videos}
