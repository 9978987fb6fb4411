"""Checkpoint files: written atomically, verified on load; an agent restored from one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from walkers.agents.factory import build_agent
from walkers.errors import CheckpointError
from walkers.training.envs import env_spaces

FORMAT_VERSION = 1


def save(state: dict, path: str | os.PathLike) -> Path:
    """Write ``state`` to ``path`` via a temporary file and an atomic rename.

    A crash mid-write leaves the previous checkpoint intact, never a truncated one; the temporary
    file a killed write left behind is removed by the next write of the same checkpoint.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format_version": FORMAT_VERSION, **state}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    for stale in path.parent.glob(f".{path.name}.*.tmp"):  # of a write killed mid-way (SIGKILL)
        stale.unlink(missing_ok=True)
    return path


def load(path: str | os.PathLike) -> dict:
    """Load a checkpoint written by :func:`save`; a damaged file raises :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # truncated zip, wrong file type, unpickling garbage ...
        raise CheckpointError(
            f"checkpoint {str(path)!r} is corrupted or truncated ({type(e).__name__}: {e})"
        ) from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {str(path)!r} is not a walkers checkpoint")
    return state


def agent_from_checkpoint(state: dict, env, device: str):
    """The run config stored in a checkpoint and its agent, restored, for acting on ``env``:
    ``(run config, agent)``."""
    run_cfg: DictConfig = OmegaConf.create(state["config"])
    run_cfg.device = device
    agent = build_agent(run_cfg, env_spaces(env))
    agent.load_state_dict(state["agent"])
    return run_cfg, agent
