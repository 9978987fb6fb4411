"""``python -m walkers.collect``: record trained policies as a Minari dataset for offline RL.

    python -m walkers.collect run_id=<id> episodes=100 dataset=walkers/walker2d/td3-expert
    python -m walkers.collect run_id=[<medium id>,<expert id>] dataset=walkers/walker2d/td3-mixed
    python -m walkers.collect run_id=<id> replay=true dataset=walkers/walker2d/td3-replay
    python -m walkers.collect run_id=random env=pendulum episodes=50 dataset=walkers/pendulum/random

Each behaviour policy (a run's checkpoint, or ``random``: uniform actions) plays ``episodes``
episodes, greedy plus optional Gaussian ``exploration_noise``; several ``run_id``s mix policies
of different quality (a "medium-expert" dataset). ``replay=true`` stores instead what a run saw
while it learned: its replay buffer, saved in ``last.pt`` when it was trained with
``save_buffer=true`` (or, where it trained, in its resume checkpoint); ``replay_steps=N`` keeps
only what it saw in its first N env steps (a "medium-replay" dataset of a run that went on to
expert level). Rewards are the env's own (no training-time shaping). The dataset's stats
(episodes, steps, return distribution, behaviour and random-policy mean return) are printed and
logged as an MLflow run tagged ``walkers.kind=dataset``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf

from walkers.agents.base import Agent
from walkers.data.episodes import Episode
from walkers.data.replay import first_steps, replay_episodes
from walkers.errors import CheckpointError, ConfigError
from walkers.tracking.client import connect, require_run, search_runs, side_run
from walkers.tracking.names import FINISHED, GRADIENT_STEPS, KIND_TAG, X_AXIS_TAG
from walkers.training.checkpoint_evaluation import fetch_checkpoint
from walkers.training.envs import make_env
from walkers.training.run import Checkpoint, RunFolder, agent_from_checkpoint

log = logging.getLogger("walkers")

RANDOM = "random"
LATEST = "latest"
#: Seeds of the random-policy episodes that measure the normalization floor.
RANDOM_REFERENCE_SEED_OFFSET = 1_000_000


@dataclass
class Behaviour:
    """One policy that generates data: a restored agent, or None for uniform random actions."""

    label: str
    agent: Agent | None
    env_cfg: DictConfig
    checkpoint: Checkpoint | None = None  # its checkpoint (replay=true reads its buffer)
    run_id: str | None = None  # the MLflow run it comes from (random, a .pt file: None)


def play(
    agent: Agent | None, env, episodes: int, seed: int, noise: float, rng: np.random.Generator
) -> list[Episode]:
    """``episodes`` recorded episodes; episode ``i`` starts from ``reset(seed=seed + i)``."""
    low, high = env.action_space.low, env.action_space.high
    half_range = (high - low) / 2
    env.action_space.seed(seed)
    recorded = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        if agent is not None:
            agent.begin_episode()
        observations, actions, rewards, terms, truncs = [obs], [], [], [], []
        done = False
        while not done:
            if agent is None:
                action = env.action_space.sample()
            else:
                action = agent.act(obs, explore=False)
                if noise > 0:
                    action = action + rng.normal(0, noise, action.shape) * half_range
                    action = np.clip(action, low, high)
            obs, reward, terminated, truncated, _ = env.step(action)
            if agent is not None:
                agent.record_reward(float(reward))
            observations.append(obs)
            actions.append(action)
            rewards.append(reward)
            terms.append(terminated)
            truncs.append(truncated)
            done = terminated or truncated
        recorded.append(
            Episode(
                observations=np.asarray(observations, dtype=np.float32),
                actions=np.asarray(actions, dtype=np.float32),
                rewards=np.asarray(rewards, dtype=np.float64),
                terminations=np.asarray(terms, dtype=bool),
                truncations=np.asarray(truncs, dtype=bool),
            )
        )
    return recorded


def _run_ids(cfg: DictConfig) -> list[str | None]:
    if cfg.run_id is None:
        return [None]  # checkpoint=<path> alone
    if isinstance(cfg.run_id, ListConfig):
        return [str(r) for r in cfg.run_id]
    return [str(cfg.run_id)]


def load_behaviours(cfg: DictConfig, client) -> list[Behaviour]:

    behaviours = []
    for run_id in _run_ids(cfg):
        if run_id == LATEST:
            run_id = latest_run(client, cfg)
        if run_id == RANDOM:
            if cfg.get("env") is None:
                raise ConfigError("run_id=random needs env=<name> (e.g. env=pendulum)")
            behaviours.append(Behaviour(RANDOM, None, cfg.env))
            continue
        if run_id is not None:
            require_run(client, run_id, cfg.tracking.uri)
        name = "last" if cfg.replay else cfg.checkpoint
        source = {"run_id": run_id, "checkpoint": name, "work_dir": cfg.work_dir}
        path = fetch_checkpoint(OmegaConf.create(source), client)
        checkpoint = Checkpoint.read(path)
        env = make_env(checkpoint.config["env"], shaping=False)
        try:
            run_cfg, agent = agent_from_checkpoint(checkpoint, env, cfg.device)
        finally:
            env.close()
        label = f"{run_cfg.algo.name} run {run_id} ({Path(path).name})" if run_id else str(path)
        behaviours.append(Behaviour(label, agent, run_cfg.env, checkpoint, run_id))
    env_ids = {b.env_cfg.id for b in behaviours}
    if cfg.get("env") is not None:
        env_ids.add(cfg.env.id)
    if len(env_ids) > 1:
        raise ConfigError(
            f"run_id={_run_ids(cfg)} mixes environments ({', '.join(sorted(env_ids))}): "
            "a dataset holds one env's episodes"
        )
    return behaviours


def latest_run(client, cfg: DictConfig) -> str:
    """The newest FINISHED training run of ``tracking.experiment`` (on ``env`` if one is given)."""
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    runs = [] if experiment is None else search_runs(client, experiment.experiment_id)
    finished = [
        r
        for r in runs
        if r.info.status == FINISHED
        and KIND_TAG not in r.data.tags
        and r.data.tags.get(X_AXIS_TAG) != GRADIENT_STEPS  # not offline runs
        and (cfg.get("env") is None or r.data.tags.get("env") == cfg.env.id)
    ]
    if not finished:
        raise ConfigError(
            f"run_id=latest: no finished training run in experiment "
            f"{cfg.tracking.experiment!r} of {cfg.tracking.uri}"
        )
    newest = max(finished, key=lambda r: r.info.start_time)
    log.info("run_id=latest: run %s (%s)", newest.info.run_id, newest.info.run_name)
    return newest.info.run_id


def _check(cfg: DictConfig) -> None:
    if not cfg.dataset:
        raise ConfigError(
            "dataset=None is not allowed: name the dataset to write, e.g. "
            "dataset=walkers/walker2d/td3-expert"
        )
    for key in ("episodes", "random_episodes"):
        if not (isinstance(cfg[key], int) and cfg[key] > 0):
            raise ConfigError(f"{key}={cfg[key]!r} is not allowed: must be an integer > 0")
    noise = cfg.exploration_noise
    if not (isinstance(noise, int | float) and noise >= 0):
        raise ConfigError(f"exploration_noise={noise!r} is not allowed: must be a number >= 0")
    if cfg.run_id is None and cfg.checkpoint in ("best", "last"):
        raise ConfigError(
            "run_id=None is not allowed with checkpoint=best|last: pass run_id=<MLflow run id>, "
            "run_id=random with env=<name>, or checkpoint=<path to a .pt file>"
        )
    if cfg.replay and RANDOM in _run_ids(cfg):
        raise ConfigError("replay=true records a run's replay buffer: run_id=random has none")
    steps = cfg.get("replay_steps")
    if steps is not None and not (cfg.replay and isinstance(steps, int) and steps > 0):
        raise ConfigError(
            f"replay_steps={steps!r} is not allowed: an integer > 0, with replay=true (the "
            "transitions of the run's first replay_steps env steps)"
        )


def collect(cfg: DictConfig) -> dict:
    """Record the dataset ``cfg`` asks for; returns its stats."""
    from walkers.data import datasets  # Minari is imported only by the commands that need it

    _check(cfg)
    if datasets.exists(cfg.dataset) and not cfg.overwrite:
        raise ConfigError(
            f"dataset={datasets.dataset_id(cfg.dataset)!r} already exists in {datasets.root()}: "
            "choose another name or version, or pass overwrite=true"
        )
    client = connect(cfg.tracking.uri) if (cfg.log_to_mlflow or cfg.run_id) else None
    behaviours = load_behaviours(cfg, client)
    env = make_env(behaviours[0].env_cfg, shaping=False)
    rng = np.random.default_rng(cfg.seed)
    episodes, per_source = [], {}
    try:
        for k, b in enumerate(behaviours):
            if cfg.replay:
                recorded = replay_episodes(replay_buffer(b, cfg))
            else:
                seed = cfg.seed + k * cfg.episodes
                recorded = play(b.agent, env, cfg.episodes, seed, cfg.exploration_noise, rng)
            log.info("%s: %d episodes", b.label, len(recorded))
            per_source[b.label] = [e.episode_return for e in recorded]
            episodes.extend(recorded)
        random_seed = cfg.seed + RANDOM_REFERENCE_SEED_OFFSET
        random_returns = [
            e.episode_return for e in play(None, env, cfg.random_episodes, random_seed, 0.0, rng)
        ]
        algos = sorted({b.agent.__class__.__name__ if b.agent else RANDOM for b in behaviours})
        description = (
            f"{'replay buffers' if cfg.replay else 'episodes'} of "
            f"{'; '.join(per_source)}; exploration_noise={cfg.exploration_noise}"
        )
        data = datasets.write(
            cfg.dataset,
            episodes,
            env,
            algorithm="+".join(algos),
            description=description,
            random_return=float(np.mean(random_returns)),
            overwrite=cfg.overwrite,
        )
    finally:
        env.close()
    stats = dataset_stats(data, per_source)
    stats["path"] = str(datasets.root() / data.id)
    if cfg.log_to_mlflow:
        sources = [b.run_id or b.label for b in behaviours]
        stats["mlflow_url"] = _log_dataset_run(client, cfg, data, stats, sources)
    return stats


def replay_buffer(b: Behaviour, cfg: DictConfig) -> dict:
    """The replay buffer ``b``'s run saved: in its logged ``last.pt`` (``save_buffer=true``), else
    in the resume checkpoint the run keeps in ``work_dir`` on the machine it trained on; cut to its
    first ``replay_steps`` env steps if asked."""
    checkpoint = b.checkpoint
    if "data" not in checkpoint.agent.get("buffer", {}) and b.run_id is not None:
        local = RunFolder.of(cfg.work_dir, b.run_id).resume_checkpoint
        if local.is_file():
            log.info("%s: the replay buffer of its resume checkpoint %s", b.label, local)
            checkpoint = Checkpoint.read(local)
    buffer = checkpoint.agent.get("buffer", {})
    if "data" not in buffer:
        raise CheckpointError(
            f"{b.label} has no replay buffer in it: train the run with save_buffer=true (its "
            "last.pt then holds the buffer), or collect where it trained (its resume checkpoint)"
        )
    if cfg.replay_steps is None:
        return buffer
    try:
        return first_steps(buffer, cfg.replay_steps, checkpoint.agent["steps"])
    except ValueError as e:
        raise ConfigError(f"replay_steps={cfg.replay_steps!r} is not allowed: {e}") from None


def dataset_stats(data, per_source: dict[str, list[float]]) -> dict:
    returns = data.returns
    return {
        "dataset": data.id,
        "env": data.env_id,
        "digest": data.digest,  # what the data is: a rebuild under its name has another
        "episodes": len(data.episodes),
        "steps": data.steps,
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "return_min": float(returns.min()),
        "return_median": float(np.median(returns)),
        "return_max": float(returns.max()),
        "behaviour_return": data.behaviour_return,
        "random_return": data.random_return,
        "sources": {label: float(np.mean(r)) for label, r in per_source.items() if r},
    }


def _log_dataset_run(client, cfg: DictConfig, data, stats: dict, sources: list[str]) -> str:
    """The dataset's stats as an MLflow run of its own, with its return histogram."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    with side_run(
        client,
        cfg.tracking.experiment,
        run_name=f"dataset-{data.id}",
        tags={KIND_TAG: "dataset", "env": data.env_id, "dataset": data.id},
        spool_dir=Path(cfg.work_dir) / "spool",
    ) as tracker:
        tracker.log_params(
            {
                "dataset": data.id,
                "digest": data.digest,
                "run_id": sources,
                "checkpoint": "last" if cfg.replay else cfg.checkpoint,
                "replay": cfg.replay,
                "episodes_per_policy": cfg.episodes,
                "exploration_noise": cfg.exploration_noise,
                "seed": cfg.seed,
            }
        )
        scalars = {k: v for k, v in stats.items() if isinstance(v, int | float)}
        tracker.log_metrics({f"dataset/{k}": v for k, v in scalars.items()}, step=0)
        for i, e in enumerate(data.episodes):
            tracker.log_metrics({"dataset/episode_return": e.episode_return}, step=i)
        out = Path(cfg.work_dir) / "datasets" / data.id
        out.mkdir(parents=True, exist_ok=True)
        (out / "stats.json").write_text(json.dumps(stats, indent=2))
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.hist(data.returns, bins=min(30, max(5, len(data.episodes) // 2)), color="tab:blue")
        for label, value, style in (
            ("behaviour mean", data.behaviour_return, "-"),
            ("random policy", data.random_return, "--"),
        ):
            ax.axvline(value, color="black", linestyle=style, label=f"{label} {value:.0f}")
        ax.set_xlabel("episode return")
        ax.set_ylabel("episodes")
        ax.set_title(data.id)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "returns.png", dpi=100)
        plt.close(fig)
        for name in ("stats.json", "returns.png"):
            tracker.log_artifact(out / name)
    return tracker.url
