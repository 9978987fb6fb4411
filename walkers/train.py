"""``python -m walkers.train``: train one agent on one environment, logged to MLflow.

    python -m walkers.train algo=td3 env=walker2d seed=3 total_steps=300000
    python -m walkers.train resume=<mlflow run id>
    python -m walkers.train 'resume=[<id>,<id>]'      # a population's members, together again
    python -m walkers.train --help | --cfg job

Builds the env and the agent from the composed config, runs the :class:`~walkers.trainer.Trainer`
and returns the value of ``optimized_metric`` (what an Optuna sweep maximizes).
"""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from omegaconf import DictConfig, OmegaConf

from walkers import PROJECT_ROOT, checkpoints, tracking
from walkers.agents.base import Agent, resolve_device
from walkers.cli import exit_on_bad_overrides
from walkers.envs import env_spaces, make_env
from walkers.errors import CheckpointError, ConfigError
from walkers.population import MEMBER_TAG, POPULATION_TAG, PopulationTrainer
from walkers.trainer import (
    RESUME_DIR,
    OfflineTrainer,
    Trainer,
    TrainerSettings,
    TrainingDiverged,
)
from walkers.trial import PRUNED_TAG, TrialReporter
from walkers.validate import is_offline, validate

log = logging.getLogger("walkers")

#: Keys a resumed run takes from the new command line; everything else comes from its checkpoint.
RESUME_OVERRIDABLE = (
    "total_steps",
    "device",
    "torch_threads",
    "progress",
    "checkpoint_every",
    "log_every",
    "save_buffer",
    "work_dir",
    "video_every",
)


#: Config-selected classes ``instantiate`` may build: agents only.
AGENT_TARGETS = ["walkers.agents.*"]


def build_agent(cfg: DictConfig, spaces: dict, **data) -> Agent:
    """Instantiate ``cfg.algo`` (its ``_target_`` class) for an env with ``spaces``.

    ``data``: what an offline agent learns from (``dataset=``); online agents take nothing more.
    """
    kwargs = OmegaConf.to_container(cfg.algo, resolve=True)
    kwargs.pop("name", None)
    try:
        # partial, then called: Hydra would turn a dataset object into a config node
        factory = hydra.utils.instantiate(
            kwargs,
            **spaces,
            device=str(resolve_device(cfg.device)),
            seed=cfg.seed,
            _convert_="all",
            _partial_=True,
            _execution_whitelist_=AGENT_TARGETS,
        )
        return factory(**data)
    except (InstantiationException, ValueError, TypeError) as e:
        cause = e.__cause__ if isinstance(e, InstantiationException) else e
        if isinstance(cause, ValueError | TypeError):  # a bad or unknown hyperparameter
            raise ConfigError(f"algo.{cause}" if "=" in str(cause) else f"algo: {cause}") from None
        raise


def agent_from_checkpoint(state: dict, env, device: str) -> tuple[DictConfig, Agent]:
    """The run config stored in a checkpoint and its agent, restored, for acting on ``env``."""
    run_cfg = OmegaConf.create(state["config"])
    run_cfg.device = device
    agent = build_agent(run_cfg, env_spaces(env))
    agent.load_state_dict(state["agent"])
    return run_cfg, agent


def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=PROJECT_ROOT,
            capture_output=True,
            text=True,
            timeout=5,
        )
        return out.stdout.strip() if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _override_keys(overrides) -> set[str]:
    return {o.split("=", 1)[0].lstrip("+~") for o in overrides}


def _load_resume_checkpoint(
    client, cfg: DictConfig, overrides, run_id: str | None = None
) -> tuple[DictConfig, dict]:
    """The run's stored config (with the allowed new overrides) and its last checkpoint."""
    run_id = str(cfg.resume) if run_id is None else run_id
    tracking.require_run(client, run_id, cfg.tracking.uri, key="resume")
    state = _last_checkpoint(client, run_id, cfg.work_dir)
    stored = OmegaConf.create(state["config"])
    given = _override_keys(overrides)
    for key in RESUME_OVERRIDABLE:
        if key in given:
            stored[key] = cfg[key]
    stored.tracking = cfg.tracking
    stored.resume = run_id
    return stored, state


def _last_checkpoint(client, run_id: str, work_dir) -> dict:
    """A run's ``last.pt``: the local resume copy (replay buffer included) where this machine
    trained the run and MLflow's is not newer, else the one uploaded to MLflow."""
    local = run_dir(work_dir, run_id) / RESUME_DIR / "last.pt"
    try:
        uploaded = tracking.download_checkpoint(client, run_id, "last.pt", work_dir)
    except CheckpointError:  # never uploaded (e.g. the store was down): the local copy will do
        if not local.is_file():
            raise
        uploaded = None
    uploaded = checkpoints.load(uploaded) if uploaded is not None else None  # damaged: an error
    if local.is_file():
        whole = checkpoints.load(local)
        if uploaded is None or whole["trainer"]["step"] >= uploaded["trainer"]["step"]:
            log.info("resuming from %s (with its replay buffer, if the agent has one)", local)
            return whole
        log.warning(
            "%s is at step %d, MLflow's last.pt at step %d: resuming from MLflow's",
            local,
            whole["trainer"]["step"],
            uploaded["trainer"]["step"],
        )
    return uploaded


def _load_population_checkpoints(
    client, cfg: DictConfig, overrides
) -> tuple[DictConfig, list[tuple[DictConfig, dict]]]:
    """``resume=[id,...]``: runs of one configuration (a population's members, typically)
    continued together as one population. Returns the population's config and, per member,
    its stored config and ``last.pt``."""
    run_ids = [str(run_id) for run_id in cfg.resume]
    listed = f"resume=[{','.join(run_ids)}]"
    if len(run_ids) < 2 or len(set(run_ids)) < len(run_ids):
        raise ConfigError(
            f"{listed}: a list resumes two or more different runs together as a "
            "population; pass a single run id to resume one run"
        )
    members = [_load_resume_checkpoint(client, cfg, overrides, run_id) for run_id in run_ids]

    def shared_settings(member_cfg: DictConfig) -> dict:
        settings = tracking.flatten(OmegaConf.to_container(member_cfg, resolve=True))
        return {k: v for k, v in settings.items() if k not in ("seed", "resume")}

    (first_cfg, first_state), first = members[0], shared_settings(members[0][0])
    for run_id, (member_cfg, state) in zip(run_ids[1:], members[1:], strict=True):
        other = shared_settings(member_cfg)
        differing = sorted(k for k in first.keys() | other.keys() if first.get(k) != other.get(k))
        if differing:
            key = differing[0]
            raise ConfigError(
                f"{listed}: runs {run_ids[0]} and {run_id} differ in {key} "
                f"({first.get(key)!r} vs {other.get(key)!r}); only runs of one configuration "
                "(seeds aside) continue together: resume the others alone"
            )
        for counter, of in (("step", "trainer"), ("num_updates", "agent")):
            if state[of][counter] != first_state[of][counter]:
                raise ConfigError(
                    f"{listed}: run {run_ids[0]} is at {counter} {first_state[of][counter]} and "
                    f"run {run_id} at {counter} {state[of][counter]}; only runs at the same step "
                    "and update continue together: resume them one by one"
                )
    population = first_cfg.copy()
    population.population = len(members)
    population.resume = run_ids
    return population, members


def train(cfg: DictConfig, overrides: list[str] | tuple = ()) -> float:
    """Train as ``cfg`` says; ``overrides`` are the command-line overrides (used by resume)."""
    resume_state = None
    _check_resume_given(cfg.resume)
    if not cfg.resume:
        validate(cfg)  # before anything is created
        warn_short_warmup(cfg)
    client = tracking.connect(cfg.tracking.uri)
    resumed_members = None
    if OmegaConf.is_list(cfg.resume):  # several runs, continued together as one population
        cfg, resumed_members = _load_population_checkpoints(client, cfg, overrides)
        validate(cfg)
    elif cfg.resume:  # the run's own config, plus the overrides allowed on resume
        cfg, resume_state = _load_resume_checkpoint(client, cfg, overrides)
        validate(cfg)
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    if cfg.population > 1:
        return _train_population(cfg, client, resumed_members)
    data = load_dataset(cfg) if is_offline(cfg) else None
    env = None if data is not None else make_env(cfg.env)  # offline agents never step an env
    eval_env = make_env(cfg.env, shaping=False)
    video_env = None
    if cfg.video_every:
        video_env = make_env(cfg.env, shaping=False, render_mode="rgb_array")
    try:
        spaces = env_spaces(eval_env)
        agent = build_agent(cfg, spaces, **({"dataset": data} if data is not None else {}))
        tracker = _open_run(client, cfg, data)
        # From here on the run exists in MLflow: every exit path below sets its final status.
        status = tracking.FAILED
        try:
            summary = _train_in_run(
                cfg, tracker, agent, env, eval_env, video_env, resume_state, data
            )
            status = tracking.FINISHED
        except KeyboardInterrupt:
            status = tracking.KILLED
            raise
        finally:
            tracker.end(status)
            log.info("MLflow run %s ended %s", tracker.run_id, status)
            log.info("open it: `make ui`, then %s", tracker.url)
            if status == tracking.KILLED:
                log.info("continue it: python -m walkers.train resume=%s", tracker.run_id)
    finally:
        for e in (env, eval_env, video_env):
            if e is not None:
                e.close()
    value = summary.get(cfg.optimized_metric, float("nan"))
    log.info("%s = %s", cfg.optimized_metric, value)
    return value


def _check_resume_given(resume) -> None:
    """``resume=`` with nothing after it (``resume=$RUN_ID`` with the variable unset) is a
    mistake, never a request for a fresh run."""
    empty = resume is not None and (
        (isinstance(resume, str) and not resume.strip())
        or (OmegaConf.is_list(resume) and len(resume) == 0)
    )
    if empty:
        raise ConfigError(
            f"resume={resume!r} is empty: pass the MLflow run id to continue (resume=<run id>, "
            "or resume=[<id>,<id>] for a population), or leave resume out to start a new run"
        )


def warn_short_warmup(cfg: DictConfig) -> None:
    """A learning-rate warm-up longer than the run never reaches ``algo.lr`` (algo=dt)."""
    warmup = OmegaConf.select(cfg, "algo.warmup_steps")
    if warmup and warmup > cfg.total_steps:
        log.warning(
            "algo.warmup_steps=%d is more than total_steps=%d: the learning rate ends at %.0f%% "
            "of algo.lr=%g; lower algo.warmup_steps (e.g. to total_steps / 10)",
            warmup,
            cfg.total_steps,
            100 * cfg.total_steps / warmup,
            cfg.algo.lr,
        )


def load_dataset(cfg: DictConfig):
    """The offline dataset ``cfg.dataset``, checked against ``cfg.env``."""
    from walkers import datasets  # Minari is imported only when a dataset is used

    data = datasets.load(cfg.dataset)
    if data.env_id is not None and data.env_id != cfg.env.id:
        raise ConfigError(
            f"dataset={data.id!r} was recorded on {data.env_id}, not on env.id={cfg.env.id!r}: "
            f"pass the env it was recorded on"
        )
    return data


def _train_population(
    cfg: DictConfig, client, resumed: list[tuple[DictConfig, dict]] | None = None
) -> float:
    """``population=K``: K members in one agent and one loop, one MLflow run per member.

    ``resumed``: per member, the stored config and ``last.pt`` of a run to continue.
    """
    k = cfg.population
    if resumed is None:
        members = [_member_config(cfg, i) for i in range(k)]
    else:
        members = [member for member, _ in resumed]
    envs = [make_env(cfg.env) for _ in members]
    eval_envs = [make_env(cfg.env, shaping=False) for _ in members]
    trackers: list[tracking.Tracker] = []
    status = tracking.FAILED
    try:
        agent = build_agent(cfg, env_spaces(eval_envs[0]), population=k)
        try:
            for i, member in enumerate(members):
                tags = {POPULATION_TAG: str(k), MEMBER_TAG: str(i)}
                trackers.append(_open_run(client, member, extra_tags=tags))
            trainers = [
                Trainer(
                    agent.member_policy(i),
                    envs[i],
                    eval_envs[i],
                    tracker,
                    trainer_settings(member),
                    checkpoint_dir=_prepare_run_dir(member, tracker) / "checkpoints",
                    checkpoint_extra={"config": OmegaConf.to_container(member, resolve=True)},
                )
                for i, (member, tracker) in enumerate(zip(members, trackers, strict=True))
            ]
            for trainer, (_, state) in zip(trainers, resumed or [], strict=False):
                trainer.restore(state)
            if resumed:
                log.info("resuming %d runs together at step %d", k, trainers[0].progress.step)
            summaries = PopulationTrainer(agent, trainers).run()
            status = tracking.FINISHED
        except KeyboardInterrupt:
            status = tracking.KILLED
            raise
        finally:
            for tracker in trackers:
                tracker.end(status)
                log.info("MLflow run %s ended %s: %s", tracker.run_id, status, tracker.url)
            if trackers:
                ids = ",".join(tracker.run_id for tracker in trackers)
                log.info("continue them together: python -m walkers.train 'resume=[%s]'", ids)
    finally:
        for e in envs + eval_envs:
            e.close()
    values = [s.get(cfg.optimized_metric, math.nan) for s in summaries]
    log.info("%s per member = %s", cfg.optimized_metric, values)
    return float(np.mean(values))


def _member_config(cfg: DictConfig, i: int) -> DictConfig:
    """Member ``i``'s config: seed ``seed + i``, and ``population=1`` (what resuming it means)."""
    member = cfg.copy()
    member.seed = cfg.seed + i
    member.population = 1
    if cfg.tracking.run_name:
        member.tracking.run_name = f"{cfg.tracking.run_name}-m{i}"
    return member


def _open_run(
    client, cfg: DictConfig, data=None, extra_tags: dict | None = None
) -> tracking.Tracker:
    """Reopen the resumed run, or create a new one with the config as params and tags.

    ``extra_tags`` are set either way (a resumed population member: its place in the population).
    """
    spool = Path(cfg.work_dir) / "spool"
    if cfg.resume:
        tracker = tracking.Tracker.reopen(client, cfg.resume, spool)
        if extra_tags:
            tracker.set_tags(extra_tags)
        return tracker
    algo, env_id, commit = cfg.algo.name, cfg.env.id, git_commit()
    tags = {
        "algo": algo,
        "env": env_id,
        "seed": str(cfg.seed),
        "git_commit": commit,
        "mlflow.source.git.commit": commit,
        tracking.X_AXIS_TAG: (OfflineTrainer if data is not None else Trainer).x_axis,
    }
    if data is not None:
        tags["dataset"] = data.id
    tags |= extra_tags or {}
    run_name = cfg.tracking.run_name or f"{algo}-{env_id}-s{cfg.seed}"
    if cfg.sweep.trial_number is not None:  # a trial of an Optuna study
        tags |= {"walkers.study": cfg.sweep.study, "walkers.trial": str(cfg.sweep.trial_number)}
        run_name = f"{cfg.sweep.study}-trial{cfg.sweep.trial_number}"
        if cfg.sweep.parent_run_id:
            tags["mlflow.parentRunId"] = cfg.sweep.parent_run_id
    tracker = tracking.Tracker.start(
        client, cfg.tracking.experiment, run_name=run_name, tags=tags, spool_dir=spool
    )
    try:
        tracker.log_params(tracking.flatten(OmegaConf.to_container(cfg, resolve=True)))
        if data is not None:
            tracker.log_params(_dataset_params(data))
    except BaseException:
        tracker.end(tracking.FAILED)
        raise
    return tracker


def run_dir(work_dir, run_id: str) -> Path:
    """A run's local folder: its checkpoints before upload, its resume copy, downloads."""
    return Path(work_dir) / "runs" / run_id


def _prepare_run_dir(cfg: DictConfig, tracker: tracking.Tracker) -> Path:
    """The run's local folder, with its ``config.yaml`` written and logged."""
    folder = run_dir(cfg.work_dir, tracker.run_id)
    config_yaml = folder / "config.yaml"
    config_yaml.parent.mkdir(parents=True, exist_ok=True)
    config_yaml.write_text(OmegaConf.to_yaml(cfg, resolve=True))
    tracker.log_artifact(config_yaml)
    return folder


def trainer_settings(cfg: DictConfig) -> TrainerSettings:
    return TrainerSettings(
        total_steps=cfg.total_steps,
        eval_every=cfg.eval_every,
        eval_episodes=cfg.eval_episodes,
        checkpoint_every=cfg.checkpoint_every,
        log_every=cfg.log_every,
        seed=cfg.seed,
        threshold=cfg.env.threshold,
        save_buffer=cfg.save_buffer,
        progress=cfg.progress,
        video_every=cfg.video_every,
        divergence_patience=cfg.divergence_patience,
    )


def _dataset_params(data) -> dict[str, str]:
    returns = data.returns
    return {
        "dataset_stats.episodes": len(data.episodes),
        "dataset_stats.steps": data.steps,
        "dataset_stats.return_mean": f"{returns.mean():.2f}",
        "dataset_stats.return_max": f"{returns.max():.2f}",
        "dataset_stats.behaviour_return": data.behaviour_return,
        "dataset_stats.random_return": data.random_return,
    }


def _train_in_run(
    cfg, tracker, agent, env, eval_env, video_env, resume_state, data=None
) -> dict[str, float]:
    reporter = TrialReporter(cfg.sweep) if cfg.sweep.trial_id is not None else None
    folder = _prepare_run_dir(cfg, tracker)
    settings = trainer_settings(cfg)
    offline = {"normalize": data.normalized} if data is not None else {}
    trainer = (OfflineTrainer if data is not None else Trainer)(
        agent,
        env,
        eval_env,
        tracker,
        settings,
        checkpoint_dir=folder / "checkpoints",
        checkpoint_extra={"config": OmegaConf.to_container(cfg, resolve=True)},
        video_env=video_env,
        on_evaluation=reporter,
        **offline,
    )
    if resume_state is not None:
        trainer.restore(resume_state)
        log.info("resuming run %s at step %d", tracker.run_id, trainer.progress.step)
    summary = trainer.run()
    if trainer.stopped_early:
        tracker.set_tags({PRUNED_TAG: trainer.progress.step})
    return summary


def parallel_jobs() -> int:
    """How many jobs Hydra's launcher runs at once (``n_jobs`` of e.g. the joblib launcher)."""
    n_jobs = HydraConfig.get().launcher.get("n_jobs") or 1
    return (os.cpu_count() or 1) if n_jobs < 0 else n_jobs


def _raise_keyboard_interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


@hydra.main(config_path="../conf", config_name="train", execution_whitelist=["walkers.*"])
def main(cfg: DictConfig) -> float:
    signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)  # SIGTERM ends the run like Ctrl-C
    jobs = parallel_jobs()
    if cfg.torch_threads is None and jobs > 1:  # parallel jobs share the cores
        cfg.torch_threads = max(1, (os.cpu_count() or 1) // jobs)
    try:
        return train(cfg, HydraConfig.get().overrides.task)
    except (ConfigError, CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except TrainingDiverged as e:
        print(f"error: {e}; MLflow run marked FAILED", file=sys.stderr)
        if cfg.sweep.trial_id is not None:
            return math.nan  # the sweeper scores a diverged trial as the worst one so far
        sys.exit(3)
    except KeyboardInterrupt:
        print("interrupted: last checkpoint saved, MLflow run marked KILLED", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    exit_on_bad_overrides("train")
    main()
