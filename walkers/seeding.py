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

An update's draws (a population's batch indices and noise) come from counter-based streams on the
device (:class:`RandomStreams`), keyed by the member's seed. A ``torch.Generator`` is one stream
per object and one draw per call, so K members with a generator each cost K calls (a Python loop)
at every draw, and a generator's state belongs to its kind of device (a CUDA generator's state
cannot be set on a CPU one). Here member k's i-th random 64-bit word is SplitMix64's (Steele, Lea,
Flood 2014): ``mix(key_k + i * golden)``, computed with int64 tensor ops (their products wrap
around, as the mix wants). So:

- the K members' next n words are one ``(K, n)`` computation, on the device;
- member k's words depend on its key and i alone: a member of a population draws exactly what a
  single run of the same seed draws;
- the state is one count of words drawn, the same on every device (a run saved on a GPU samples
  on, unchanged, on a CPU);
- a draw is nothing but tensor ops, and the count a device tensor advanced in place, so a CUDA
  graph can capture it.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Sequence

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


# --- counter-based streams on the device: a population's draws in one op ---------------------
GOLDEN = 0x9E3779B97F4A7C15
MIX_1 = 0xBF58476D1CE4E5B9
MIX_2 = 0x94D049BB133111EB


def as_int64(x: int) -> int:
    """The int64 whose bits are those of the unsigned 64-bit ``x``."""
    x %= 1 << 64
    return x - (1 << 64) if x >= 1 << 63 else x


def shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 words (torch's ``>>`` is arithmetic: it copies the sign)."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def splitmix64(state: torch.Tensor) -> torch.Tensor:
    """SplitMix64's output function of int64 ``state`` words (the state already advanced)."""
    z = (state ^ shift_right(state, 30)) * as_int64(MIX_1)
    z = (z ^ shift_right(z, 27)) * as_int64(MIX_2)
    return z ^ shift_right(z, 31)


def stream_key(seed: int, stream: str) -> int:
    """A 64-bit key for ``stream`` of run ``seed`` (from :func:`stream_seeds`)."""
    high, low = stream_seeds(seed, stream, 2)
    return (high << 32) | low


class RandomStreams:
    """One random stream per key (per member), all drawn together: each draw returns ``(K, ...)``
    values, row k from stream k. ``drawn`` counts the words each stream has given."""

    def __init__(self, keys: Sequence[int], device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.keys = torch.tensor([as_int64(k) for k in keys], dtype=torch.int64, device=self.device)
        self.drawn = torch.zeros((), dtype=torch.int64, device=self.device)

    @classmethod
    def of_seeds(cls, seeds: Sequence[int], stream: str, device="cpu") -> RandomStreams:
        """The streams named ``stream`` of runs ``seeds`` (a population's members' seeds)."""
        return cls([stream_key(seed, stream) for seed in seeds], device)

    def words(self, n: int) -> torch.Tensor:
        """The next ``n`` 64-bit words of every stream, ``(K, n)`` int64."""
        i = self.drawn + torch.arange(1, n + 1, device=self.device)
        self.drawn += n
        return splitmix64(self.keys[:, None] + i * as_int64(GOLDEN))

    def integers(self, high: int | torch.Tensor, n: int) -> torch.Tensor:
        """``(K, n)`` integers uniform in ``[0, high)`` (63-bit words modulo ``high``: a bias
        of order ``high / 2**63``)."""
        return shift_right(self.words(n), 1) % high

    def uniform(self, n: int) -> torch.Tensor:
        """``(K, n)`` float32 uniforms in ``[0, 1)`` (24-bit: each a multiple of 2**-24)."""
        return shift_right(self.words(n), 40).to(torch.float32) * 2.0**-24

    def normal(self, shape: Sequence[int]) -> torch.Tensor:
        """``(K, *shape)`` float32 standard normals (Box-Muller on two 24-bit uniforms per
        word: tails end at about 5.8 sigma)."""
        words = self.words(math.prod(shape))
        scale = 2.0**-24
        u1 = (shift_right(words, 40) + 1).to(torch.float32) * scale  # (0, 1]
        u2 = ((words >> 8) & 0xFFFFFF).to(torch.float32) * scale  # [0, 1)
        z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
        return z.view(len(self.keys), *shape)

    def normal_like(self, x: torch.Tensor) -> torch.Tensor:
        """Standard normals shaped like ``x``, whose first dimension is the K streams'."""
        return self.normal(x.shape[1:])

    def state_dict(self) -> dict:
        """The keys and the count: a checkpoint's streams go on wherever it is loaded."""
        return {"keys": [k % (1 << 64) for k in self.keys.tolist()], "drawn": int(self.drawn)}

    def member_state_dict(self, i: int) -> dict:
        """Stream ``i``'s as a single stream's :meth:`state_dict`."""
        return {"keys": [int(self.keys[i]) % (1 << 64)], "drawn": int(self.drawn)}

    def load_state_dict(self, state: dict) -> None:
        self.keys.copy_(torch.tensor([as_int64(k) for k in state["keys"]], dtype=torch.int64))
        self.drawn.fill_(int(state["drawn"]))

    def load_member_state_dict(self, i: int, state: dict) -> None:
        """A single stream's state into stream ``i`` (the count is the streams' in common)."""
        (key,) = state["keys"]
        self.keys[i] = as_int64(key)
        self.drawn.fill_(int(state["drawn"]))
