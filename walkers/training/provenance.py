"""What a training run records about itself: its tags (algorithm, env, seed, implementation,
commit, worker, the digest of the code that trains it, a sweep job's place), its name, and its
config as shareable params (no secrets).

Readers of runs (``walkers.compare``, a study's checks) import its names too, so it imports
neither torch nor gymnasium (the code digest reads the source files, not the modules): a report
or a refusal does not wait seconds for them."""

from __future__ import annotations

import functools
import hashlib
import socket
import subprocess
import sys
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from walkers import PROJECT_ROOT
from walkers.secrets import redacted, redacted_uri
from walkers.tracking.names import JOB_KEY_TAG, X_AXIS_TAG

#: Tag: the digest of the code a run was trained by (:func:`code_digest`).
CODE_DIGEST_TAG = "walkers.code_digest"
#: Tag: the versions of the packages that compute a run (:data:`PACKAGES`).
PACKAGES_TAG = "walkers.packages"
PACKAGES = ("walkers", "torch", "numpy", "gymnasium", "mujoco", "box2d", "stable-baselines3",
            "sb3-contrib", "mlflow")  # fmt: skip
#: Tag: the machine (and Ray node) that trains the run; a resumed run: the latest one.
WORKER_TAG = "walkers.worker"
#: Tags of a population member's run: the population's size, the member's place in it.
POPULATION_TAG = "walkers.population"
MEMBER_TAG = "walkers.population_member"
#: Tag: what identifies a plain command's runs across attempts (the same command continues
#: them: :func:`walkers.training.command_plan.command_key`).
COMMAND_KEY_TAG = "walkers.command_key"
#: Tag of an earlier attempt's run that a job run again could not continue (it is FAILED).
SUPERSEDED_TAG = "walkers.superseded"
#: Tag of a run that ended FAILED because its updates diverged (the step): a rerun would too.
DIVERGED_TAG = "walkers.diverged_at_step"


#: In a job's key, what each of its runs replaces by its own seed (a study's population job:
#: each member run is keyed as the single job of its seed would be).
SEED_IN_KEY = "{seed}"


def job_key_of_seed(job_key: str | None, seed: int) -> str | None:
    """The key of the job's run of ``seed``: ``job_key`` with :data:`SEED_IN_KEY` filled in."""
    return job_key.replace(SEED_IN_KEY, str(seed)) if job_key else job_key


def new_run_tags(cfg: DictConfig, x_axis: str, data=None) -> dict[str, str]:
    """The tags a new run starts with; ``x_axis``: what its steps count; ``data``: an offline
    run's data (:class:`~walkers.training.command_plan.RunDataset`)."""
    commit = git_commit()
    tags = {
        CODE_DIGEST_TAG: code_digest(),
        PACKAGES_TAG: package_versions(),
        "algo": cfg.algo.name,
        "env": cfg.env.id,
        "seed": str(cfg.seed),
        "impl": cfg.get("impl", "walkers"),
        WORKER_TAG: worker_name(),
        "git_commit": commit,
        "mlflow.source.git.commit": commit,
        X_AXIS_TAG: x_axis,
    }
    if data is not None:
        tags["dataset"] = data.dataset.id
    if cfg.job_key:
        tags[JOB_KEY_TAG] = cfg.job_key
    return tags


@functools.cache
def code_digest() -> str:
    """The digest of what computes an update: the source of ``walkers.agents`` and
    ``walkers.data``, and the torch version. Read once per process (as the code is loaded
    once): a multirun's later jobs must not record files edited after their process started."""
    root = Path(__file__).resolve().parents[1]
    try:
        torch_version = metadata.version("torch")  # torch.__version__, without importing torch
    except metadata.PackageNotFoundError:  # a torch built in place, without package metadata
        import torch

        torch_version = torch.__version__
    digest = hashlib.sha256(torch_version.encode())
    for package in ("agents", "data"):
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def resumed_code_tags(tags_before: Mapping[str, str]) -> dict[str, str]:
    """The code-digest tag of a run resumed by this process: unchanged when this code trained it
    before, else every digest that trained it, joined by ``+`` (``a+b``). Such a run's update can
    no longer be fingerprinted by one code, so it cannot stand as a reference arm: an export
    records no fingerprint for it (:func:`walkers.analysis.fingerprint.of_run`)."""
    before, now = tags_before.get(CODE_DIGEST_TAG), code_digest()
    if before is None or now in code_digests(tags_before):
        return {}
    return {CODE_DIGEST_TAG: f"{before}+{now}"}


def code_digests(tags: Mapping[str, str]) -> list[str]:
    """Every code digest that trained a run, in order (one, unless it was resumed by other
    update code: :func:`resumed_code_tags`); none for a run from before the tag."""
    return [digest for digest in tags.get(CODE_DIGEST_TAG, "").split("+") if digest]


def package_versions() -> str:
    """The versions of the packages a run's numbers depend on, in one line."""
    versions = []
    for name in PACKAGES:
        try:
            versions.append(f"{name}=={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return " ".join(versions)


def run_name(cfg: DictConfig) -> str:
    """``tracking.run_name``, else ``<algo>[-sb3]-<env>-s<seed>``; a study's trial:
    ``<study>-trial<n>[-s<seed>]``."""
    if cfg.trial.number is not None:
        name = f"{cfg.trial.study}-trial{cfg.trial.number}"
        return name + (f"-s{cfg.seed}" if cfg.seeds_per_trial > 1 else "")
    twin = "-sb3" if cfg.get("impl") == "sb3" else ""
    return cfg.tracking.run_name or f"{cfg.algo.name}{twin}-{cfg.env.id}-s{cfg.seed}"


def trial_tags(cfg: DictConfig) -> dict[str, str]:
    """A sweep job's place in its study: the study, the trial, the MLflow run it nests under
    (set again on resume: a retried trial of a study continues the run of the trial it
    retries)."""
    tags = {}
    if cfg.trial.number is not None:
        tags = {"walkers.study": cfg.trial.study, "walkers.trial": str(cfg.trial.number)}
    if cfg.trial.parent_run_id:  # an Optuna study's trial, or an A/B study's job
        tags["mlflow.parentRunId"] = cfg.trial.parent_run_id
    return tags


def worker_name() -> str:
    """Where the run trains: the host, and the Ray node when a Ray cluster runs the job."""
    host = socket.gethostname()
    if "ray" in sys.modules:  # only a Ray launcher's job has it imported
        import ray

        if ray.is_initialized():
            return f"{host}/ray-node-{ray.get_runtime_context().get_node_id()[:12]}"
    return host


def shareable(cfg: DictConfig) -> dict:
    """The resolved config as MLflow params, ``config.yaml`` and checkpoints hold it: without
    the study database's password (jobs get theirs from the sweeper, never from a stored
    config)."""
    data = OmegaConf.to_container(cfg, resolve=True)
    for node in ("trial", "optuna"):
        if isinstance(data.get(node), dict) and data[node].get("storage"):
            data[node]["storage"] = redacted(data[node]["storage"])
    if isinstance(data.get("tracking"), dict) and data["tracking"].get("uri"):
        data["tracking"]["uri"] = redacted_uri(data["tracking"]["uri"])
    return data


@functools.cache
def git_commit() -> str:
    """The commit the code runs from (provenance tag), or "unknown": read once per process, so
    the later jobs of a multirun run in one process (the basic launcher's) name the commit of the
    code the process loaded, not a checkout that moved on while they waited."""
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


#: The params that say which data an offline run learned from, beyond its dataset's name: its
#: digest (a hash of the episodes), and for runs from before the digest, the data's statistics
#: and the references its normalized scores were measured between.
DATA_DIGEST = "dataset_stats.digest"
DATA_STATS_KEYS = (
    "dataset_stats.episodes",
    "dataset_stats.steps",
    "dataset_stats.return_mean",
    "dataset_stats.return_max",
)
DATA_REFERENCE_KEYS = ("dataset_stats.behaviour_return", "dataset_stats.random_return")


def other_data(recorded: dict[str, str], now: dict[str, str]) -> str | None:
    """How the data of ``now`` (a dataset's :func:`dataset_params`, or another run's params)
    differs from the data a run ``recorded``, in words (``digest a then, b now``); None when it
    is the same data. Digests decide where the run has one; the statistics otherwise. The
    references count in both cases: the same episodes with another random-policy score give
    other normalized scores."""
    keys = (DATA_DIGEST,) if recorded.get(DATA_DIGEST) else DATA_STATS_KEYS
    for key in (*keys, *DATA_REFERENCE_KEYS):
        then, current = recorded.get(key), now.get(key)
        if then is not None and current is not None and then != str(current):
            return f"{key.removeprefix('dataset_stats.')} {then} then, {current} now"
    return None


def dataset_params(data, references) -> dict[str, str]:
    """An offline run's dataset statistics, as params, with the ``references`` its normalized
    scores are measured between and the behaviour policy's own score on them."""
    returns = data.returns
    behaviour = data.behaviour_return
    behaviour_score = None if behaviour is None else references.normalized(behaviour)
    return {
        **references.as_params(),
        "dataset_stats.behaviour_score": None
        if behaviour_score is None
        else f"{behaviour_score:.2f}",
        DATA_DIGEST: data.digest,
        "dataset_stats.episodes": len(data.episodes),
        "dataset_stats.steps": data.steps,
        "dataset_stats.return_mean": f"{returns.mean():.2f}",
        "dataset_stats.return_max": f"{returns.max():.2f}",
        "dataset_stats.behaviour_return": data.behaviour_return,
        "dataset_stats.random_return": data.random_return,
    }
