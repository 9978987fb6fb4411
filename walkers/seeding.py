"""Every random stream of a run, derived from the run's seed.

A run's streams (its training env, its evaluation start states, exploration noise, replay
sampling, policy sampling) come from ``numpy.random.SeedSequence(seed, spawn_key=(stream,))``:
statistically independent of each other within a run, and between seeds. Seeds of a study are
then independent samples: seed 1 never starts an episode where seed 0 did (a plain ``seed + i``
scheme shares almost every start state between neighbouring seeds), yet the same seed and config
reproduce a run exactly.

The training env is seeded once, at its first reset, and then runs on its own RNG (Gymnasium's
convention); that RNG's state goes into every checkpoint, so a resumed run draws the start states
the uninterrupted run would have drawn. Evaluations use a fixed set of start states per run (the
same at every evaluation, so evaluations are comparable across checkpoints).
"""

from __future__ import annotations

import hashlib
import logging

import gymnasium as gym
import numpy as np
import torch

log = logging.getLogger("walkers")

#: The named streams of a run; a number is a stream's spawn key: never renumber one.
STREAMS = {
    "train_env": 0,  # the training env's first reset (then its own RNG runs)
    "eval_env": 1,  # evaluation episode i starts from reset(seed=eval_start_seeds(...)[i])
    "exploration": 2,  # off-policy warm-up actions and exploration noise
    "replay": 3,  # replay buffer / dataset batch sampling, PPO's minibatch shuffling
    "policy": 4,  # stochastic policies' action sampling (REINFORCE, PPO); SB3's one seed
    "held_out_eval": 5,  # walkers.evaluate's default start states: never seen by the run
    "update_noise": 6,  # the off-policy updates' noise (TD3's target smoothing, SAC's actions)
}


def stream_seeds(seed: int, stream: str, n: int = 1) -> list[int]:
    """``n`` 32-bit seeds of ``stream`` of run ``seed`` (the first k are the same for any n)."""
    sequence = np.random.SeedSequence(seed, spawn_key=(STREAMS[stream],))
    return [int(s) for s in sequence.generate_state(n)]


def numpy_rng(seed: int, stream: str) -> np.random.Generator:
    """A numpy generator for ``stream`` of run ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(STREAMS[stream],)))


def torch_generator(seed: int, stream: str, device: torch.device | str = "cpu") -> torch.Generator:
    """A torch generator for ``stream`` of run ``seed``."""
    generator = torch.Generator(device=device)
    generator.manual_seed(stream_seeds(seed, stream)[0])
    return generator


def restore_generator(generator: torch.Generator, saved: torch.Tensor, what: str) -> None:
    """Set ``generator`` to a checkpoint's state of it, where that was saved on the same kind of
    device. A CPU and a CUDA generator's states differ in size and layout: a run trained on a GPU
    and loaded on a CPU (or back) goes on with a stream seeded from the saved state, so loading
    the same checkpoint twice still draws the same numbers, and a warning says they differ from
    the ones the run would have drawn."""
    try:
        generator.set_state(saved)
    except RuntimeError:
        digest = hashlib.sha256(saved.cpu().numpy().tobytes()).digest()
        generator.manual_seed(int.from_bytes(digest[:8], "little"))
        log.warning(
            "%s was saved on another kind of device than %s: it goes on with a stream seeded "
            "from the saved one, so its draws differ from the ones the run would have made",
            what,
            generator.device.type,
        )


def eval_start_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of a run's ``episodes`` evaluation episodes (the same at every evaluation)."""
    return stream_seeds(seed, "eval_env", episodes)


def training_env_seed(seed: int) -> int:
    """The seed of the first reset of run ``seed``'s training env (then its own RNG runs)."""
    return stream_seeds(seed, "train_env")[0]


def held_out_start_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds no periodic evaluation of run ``seed`` used: ``best.pt`` was chosen on those,
    so its score on them is flattered; these give it an unbiased one."""
    return stream_seeds(seed, "held_out_eval", episodes)


def first_training_reset(env: gym.Env, seed: int):
    """Reset the training env of run ``seed`` for its first episode: ``(obs, info)``."""
    return env.reset(seed=training_env_seed(seed))


def env_rng_state(env: gym.Env | gym.vector.VectorEnv, member: int | None = None) -> dict:
    """The training env's RNG state (what its next resets will draw), for a checkpoint; of a
    vector env, each of its envs' (``{"envs": [...]}``), or with ``member`` that one env's alone
    (a population member's env, in this process or in a worker of its own)."""
    if isinstance(env, gym.vector.VectorEnv):
        states = [generator.bit_generator.state for generator in env.get_attr("np_random")]
        return {"envs": states} if member is None else states[member]
    return env.unwrapped.np_random.bit_generator.state


def restore_env_rng(
    env: gym.Env | gym.vector.VectorEnv, state: dict, member: int | None = None
) -> None:
    """Continue the training env's RNG from a checkpoint (before its next, unseeded reset): a
    vector env's envs from ``{"envs": [...]}``, or with ``member`` that one env from its own."""
    if isinstance(env, gym.vector.VectorEnv):
        generators = list(env.get_attr("np_random"))
        if member is None:
            generators = [_generator_at(one) for one in state["envs"]]
        else:
            generators[member] = _generator_at(state)
        env.set_attr("np_random", generators)
        return
    env.unwrapped.np_random = _generator_at(state)


def _generator_at(state: dict) -> np.random.Generator:
    generator = np.random.Generator(getattr(np.random, state["bit_generator"])())
    generator.bit_generator.state = state
    return generator


def torch_rng_state() -> dict:
    """torch's global generators, as a checkpoint keeps them: the CPU's (``torch_rng``) and,
    when the run uses CUDA, every CUDA device's (``cuda_rng``; None otherwise). Updates draw
    from them (TD3's target smoothing noise on the agent's device)."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None
    return {"torch_rng": torch.get_rng_state(), "cuda_rng": cuda}


def restore_torch_rng(state: dict) -> None:
    """Set torch's generators back to a checkpoint's :func:`torch_rng_state`."""
    torch.set_rng_state(state["torch_rng"])
    cuda = state.get("cuda_rng")
    if cuda is None:
        return
    if torch.cuda.is_available() and torch.cuda.device_count() == len(cuda):
        torch.cuda.set_rng_state_all(cuda)
    else:
        log.warning(
            "the checkpoint's CUDA random state (%d devices) cannot be restored on this machine "
            "(%d devices): updates draw other noise than the run would have",
            len(cuda),
            torch.cuda.device_count() if torch.cuda.is_available() else 0,
        )
