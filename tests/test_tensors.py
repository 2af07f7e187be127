"""The shared tensor helpers (``evdown_torch._tensors``) against plain torch."""

from __future__ import annotations

import pytest
import torch

from evdown_torch._tensors import stable_sort_small


@pytest.mark.parametrize("n", [0, 100, 4096, 8191, 8192, 9000, 32767, 40000])
@pytest.mark.parametrize("bound", [7, 256, 257, 1 << 15, 921_600])
def test_padded_sort_is_the_stable_sort(n, bound, rng):
    # Keys padded to radix-sort length (ties with the padding key bound - 1 included) must
    # sort exactly as torch's plain stable sort.
    keys = torch.as_tensor(rng.integers(0, bound, n))
    keys[: n // 3] = bound - 1
    values, order = stable_sort_small(keys, bound)
    expected = torch.sort(keys, stable=True)
    assert torch.equal(values, expected.values)
    assert torch.equal(order, expected.indices)


@pytest.mark.parametrize(
    ("bound", "dtype"),
    [(7, torch.int16), (256, torch.int16), (257, torch.int16), (1 << 15, torch.int16),
     ((1 << 15) + 1, torch.int32),
     (1 << 31, torch.int32), ((1 << 31) + 1, torch.int64)],
)
@pytest.mark.parametrize("n", [100, 9000, 40000])
def test_narrow_sort_returns_the_keys_in_the_dtype_they_were_sorted_as(bound, dtype, n, rng):
    keys = torch.as_tensor(rng.integers(0, bound, n))
    keys[: n // 4] = bound - 1
    values, order = stable_sort_small(keys, bound, narrow=True)
    expected = torch.sort(keys, stable=True)
    assert values.dtype == dtype and order.dtype == torch.int64
    assert torch.equal(values.to(torch.int64), expected.values)
    assert torch.equal(order, expected.indices)
