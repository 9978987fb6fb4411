"""Counter-based random streams: one per member of a population, drawn for all members in one op.

A ``torch.Generator`` is one stream per object and one draw per call, so K members with a
generator each cost K calls (a Python loop) at every draw, and a generator's state belongs to its
kind of device (a CUDA generator's state cannot be set on a CPU one). Here member k's i-th random
64-bit word is SplitMix64's (Steele, Lea, Flood 2014): ``mix(key_k + i * golden)``, computed with
int64 tensor ops (their products wrap around, as the mix wants). So:

- the K members' next n words are one ``(K, n)`` computation, on the device;
- member k's words depend on its key and i alone: a member of a population draws exactly what a
  single run of the same seed draws;
- the state is one count of words drawn, the same on every device (a run saved on a GPU samples
  on, unchanged, on a CPU);
- a draw is nothing but tensor ops, and the count a device tensor advanced in place, so a CUDA
  graph can capture it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from walkers.seeding import stream_seeds

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
    """A 64-bit key for ``stream`` of run ``seed`` (from :func:`walkers.seeding.stream_seeds`)."""
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
