"""The compiled stable sorts (``compiled/sorting.py``) against NumPy's stable ``argsort``."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")
from evdown_torch.transforms.functional.compiled.sorting import (  # noqa: E402
    merge_order,
    stable_order,
)

KEYS = [
    [], [5], [3, 3, 1, 3, 1], [7, 7, 7, 7], [4, 3, 2, 1, 0],
    [2**63 - 1, 2**63 - 2**62, 2**62 + 5, 2**63 - 1, 2**62],  # near int64's top
    [-(2**63), -1, -(2**63), 5 - 2**63],  # and its bottom
    np.random.default_rng(1).integers(-(2**62), 2**62 - 1, 3000),  # six radix digits
    np.random.default_rng(2).integers(0, 30, 3000),  # one digit, many ties
    np.random.default_rng(3).integers(0, 1 << 23, 3000),  # three digits
    np.random.default_rng(4).integers(0, 16, 37),  # a region's few pixels (odd length)
]


@pytest.mark.parametrize("keys", KEYS)
@pytest.mark.parametrize("order", [stable_order, merge_order])
def test_the_order_is_the_stable_sort_order(keys, order):
    values = np.asarray(keys, dtype=np.int64)
    got = order(values)
    assert got.dtype == np.int64
    assert np.array_equal(got, np.argsort(values, kind="stable"))


@pytest.mark.parametrize("n", range(1, 20))
def test_merge_order_keeps_ties_in_place_at_every_length(n):
    # Every run split (lengths that are not powers of two): ties between runs keep the left.
    keys = np.arange(n, dtype=np.int64) % 3
    assert np.array_equal(merge_order(keys), np.argsort(keys, kind="stable"))
    assert np.array_equal(merge_order(keys[::-1].copy()), np.argsort(keys[::-1], kind="stable"))


def test_the_radix_order_refuses_a_span_past_int64():
    # A wrapped range (a LinearEstimation state's knots span less than 2**53, check_span)
    # is refused, not sorted wrongly.
    with pytest.raises(ValueError, match="2\\*\\*63 or more"):
        stable_order(np.array([-(2**63), 2**63 - 1], dtype=np.int64))


@pytest.mark.parametrize("seed", range(3))
def test_merge_order_of_float_times_is_the_stable_sort_order(seed):
    # The held knots' times (float64 timestamps): ties, negative values and fractions.
    rng = np.random.default_rng(seed)
    times = np.round(rng.normal(0.0, 1e6, 501), 1) / 3
    times[::7] = times[0]
    assert np.array_equal(merge_order(times), np.argsort(times, kind="stable"))
