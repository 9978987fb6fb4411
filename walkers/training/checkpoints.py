"""A run's checkpoints (``last.pt``, ``best.pt``): what they hold (:class:`Checkpoint`, the one
type that writes and reads them), the files written atomically and verified on load, and an
agent restored from one."""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from dataclasses import dataclass
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


@dataclass(frozen=True)
class Checkpoint:
    """What a run's checkpoint holds, by name (the file holds the same names, as a dict).

    ``trainer`` is the loop's progress (:class:`walkers.training.bookkeeping.Progress` as a
    dict), ``agent`` the agent's state (with or without its replay buffer), ``config`` the
    run's composed config (shareable: no secrets), ``torch_rng`` and ``cuda_rng`` torch's
    generators (:func:`walkers.seeding.torch_rng_state`), ``env_rng`` the training env's
    generator (None for a run without one: offline).
    """

    trainer: dict
    agent: dict
    config: dict
    torch_rng: torch.Tensor
    cuda_rng: list | None = None
    env_rng: dict | None = None

    @property
    def step(self) -> int:
        """The run's step when it was written (env steps; offline: gradient steps)."""
        return self.trainer["step"]

    @property
    def num_updates(self) -> int | None:
        return self.agent.get("num_updates")

    @property
    def progress(self) -> dict:
        """The loop's progress to go on from; a checkpoint from before runs counted their CPU
        time has a total that is unknown, not 0."""
        return {"cpu_seconds": math.nan} | self.trainer

    def run_config(self) -> DictConfig:
        return OmegaConf.create(self.config)

    def with_agent(self, agent: dict) -> Checkpoint:
        """This checkpoint with another agent state (the same agent with its replay buffer)."""
        return dataclasses.replace(self, agent=agent)

    def write(self, path: str | os.PathLike) -> Path:
        """Write it to ``path`` atomically (:func:`save`); its tensors are written, not copied."""
        return save({f.name: getattr(self, f.name) for f in dataclasses.fields(self)}, path)

    @classmethod
    def read(cls, path: str | os.PathLike) -> Checkpoint:
        """The checkpoint at ``path``; a damaged or foreign file raises :class:`CheckpointError`."""
        state = load(path)
        required = [f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING]
        if missing := [name for name in required if name not in state]:
            raise CheckpointError(
                f"checkpoint {str(path)!r} holds no {missing[0]}: not a training run's checkpoint"
            )
        return cls.of(state)

    @classmethod
    def of(cls, state: dict) -> Checkpoint:
        """A checkpoint from the dict a file holds (:func:`load`)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{key: value for key, value in state.items() if key in names})


def agent_from_checkpoint(checkpoint: Checkpoint | dict, env, device: str):
    """The run config stored in a checkpoint (or the dict a file holds: :func:`load`) and its
    agent, restored, for acting on ``env``: ``(run config, agent)``."""
    if isinstance(checkpoint, dict):
        checkpoint = Checkpoint.of(checkpoint)
    run_cfg = checkpoint.run_config()
    run_cfg.device = device
    agent = build_agent(run_cfg, env_spaces(env))
    agent.load_state_dict(checkpoint.agent)
    return run_cfg, agent
