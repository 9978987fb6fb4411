"""The counter-based random streams of walkers.seeding: SplitMix64 to the bit, a member's
stream independent of its population, a saved state that continues. The replay buffer that samples
with them: ``tests/data/test_replay.py``."""

from __future__ import annotations

import pytest
import torch

from walkers.seeding import GOLDEN, MIX_1, MIX_2, RandomStreams, stream_key

MASK = (1 << 64) - 1


def textbook_splitmix64(seed: int, n: int) -> list[int]:
    """SplitMix64 as published (Steele, Lea, Flood 2014), in Python's unbounded ints."""
    state, words = seed & MASK, []
    for _ in range(n):
        state = (state + GOLDEN) & MASK
        z = state
        z = ((z ^ (z >> 30)) * MIX_1) & MASK
        z = ((z ^ (z >> 27)) * MIX_2) & MASK
        words.append(z ^ (z >> 31))
    return words


def test_the_words_are_splitmix64s_to_the_bit():
    keys = [0, 1, 2**63 + 5, 0xDEADBEEFCAFEF00D]
    streams = RandomStreams(keys)
    first, then = streams.words(5), streams.words(3)  # drawn in two goes: the stream goes on
    got = torch.cat([first, then], dim=1)
    for key, row in zip(keys, got, strict=True):
        assert [w & MASK for w in row.tolist()] == textbook_splitmix64(key, 8)


def test_a_members_draws_do_not_depend_on_its_population():
    """Row k of the streams of seeds (3, 4, 5) is what the streams of seed 4 alone draw."""
    population = RandomStreams.of_seeds([3, 4, 5], "replay")
    single = RandomStreams.of_seeds([4], "replay")
    assert torch.equal(population.integers(1000, 64)[1], single.integers(1000, 64)[0])
    assert torch.equal(population.normal((32, 6))[1], single.normal((32, 6))[0])
    assert stream_key(4, "replay") != stream_key(4, "update_noise")  # streams of a run differ


def test_integers_are_uniform_and_normals_standard():
    streams = RandomStreams.of_seeds([0, 1], "replay")
    draws = streams.integers(10, 50_000)
    assert draws.min() >= 0 and draws.max() <= 9
    counts = torch.bincount(draws.flatten(), minlength=10).numpy()
    # 10,000 expected per bin: a chi-square of 9 degrees of freedom, far below its 0.1% tail (27.9)
    assert ((counts - 10_000) ** 2 / 10_000).sum() < 27.9
    z = streams.normal((100_000,))
    assert abs(z.mean().item()) < 0.01 and abs(z.std().item() - 1) < 0.01
    assert z.abs().max().item() < 5.8  # Box-Muller on 24-bit uniforms: no infinite tails
    assert abs((z.abs() < 1.96).float().mean().item() - 0.95) < 0.005


def test_a_saved_state_continues_the_streams():
    a = RandomStreams.of_seeds([7, 8], "update_noise")
    a.normal((10,))
    saved = a.state_dict()
    assert saved == {"keys": [stream_key(s, "update_noise") for s in (7, 8)], "drawn": 10}
    b = RandomStreams.of_seeds(
        [0, 1], "update_noise"
    )  # another run's: the keys come with the state
    b.load_state_dict(saved)
    assert torch.equal(a.normal((4, 3)), b.normal((4, 3)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_gpu_draws_the_cpus_integers():
    cpu, gpu = (RandomStreams.of_seeds([3, 4], "replay", device) for device in ("cpu", "cuda"))
    assert torch.equal(cpu.integers(10_000, 256), gpu.integers(10_000, 256).cpu())
