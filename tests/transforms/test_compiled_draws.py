"""The subsamplers' draws: the compiled pass against the eager chains and a Python reference."""

from __future__ import annotations

import pytest
import torch

from evdown_torch import Events
from evdown_torch.transforms.functional.draws import event_uniforms, mixed_seed
from tests.helpers import assert_identical, both_paths

pytest.importorskip("numba")


def _fmix32(h: int) -> int:
    """MurmurHash3's 32-bit finaliser, in Python integers."""
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & 0xFFFFFFFF
    return h ^ (h >> 16)


def reference_uniform(seed: int, index: int, x: int, y: int, p: bool, offset_bits: int) -> float:
    """docs/semantics.md's draw of one event, word by word (two chains, 53 bits)."""
    key = mixed_seed(b"evdown_torch event uniforms", seed)
    words = [index, index >> 32, x, (y << 1) | int(p), offset_bits, offset_bits >> 32]
    chains = []
    for start in (key & 0xFFFFFFFF, (key >> 32) & 0xFFFFFFFF):
        h = start
        for word in words:
            h = _fmix32(h ^ (word & 0xFFFFFFFF))
        chains.append(h)
    return ((chains[0] << 21) | (chains[1] >> 11)) * 2.0**-53


@pytest.mark.parametrize("t_dtype", [torch.int64, torch.float64])
def test_compiled_draws_equal_the_eager_ones_and_the_reference(t_dtype, rng):
    n = 3_000
    x = torch.from_numpy(rng.integers(0, 2**20, n))
    y = torch.from_numpy(rng.integers(0, 2**20, n))
    p = torch.from_numpy(rng.random(n) < 0.5)
    if t_dtype == torch.int64:  # offsets past 2**32, and below the origin
        t = torch.from_numpy(rng.integers(-2**40, 2**62, n))
    else:
        t = torch.from_numpy(rng.normal(0.0, 1e9, n))
    events = Events(x, y, t, p)
    index = torch.from_numpy(rng.integers(0, 2**40, n))  # positions past 2**32 too
    origin = 12_345 if t_dtype == torch.int64 else 1.5
    compiled, eager = both_paths(lambda: event_uniforms(events, 7, index=index, origin=origin))
    assert_identical(compiled, eager)
    offset = t - origin
    bits = offset.view(torch.int64) if t_dtype == torch.float64 else offset
    for i in range(0, n, 300):
        want = reference_uniform(7, int(index[i]), int(x[i]), int(y[i]), bool(p[i]),
                                 int(bits[i]))
        assert float(compiled[i]) == want
    assert float(compiled.min()) >= 0.0 and float(compiled.max()) < 1.0
