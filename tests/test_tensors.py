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
    narrow, narrow_order = stable_sort_small(keys, bound, int64_keys=False)
    assert narrow.dtype == (torch.uint8 if bound <= 256 else torch.int16 if bound <= 1 << 15
                            else torch.int32)
    assert torch.equal(narrow.long(), expected.values)
    assert torch.equal(narrow_order, expected.indices)
