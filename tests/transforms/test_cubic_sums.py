"""The cubic kernel's mid-segment sums do not depend on how their pairs are chunked.

``_mid_segment_sums`` evaluates every (segment, breakpoint strictly inside it) pair in chunks of
``CHUNK`` pairs, finding each pair's segment and breakpoint from the chunk's first pair; the
sums must be the same floats, bit for bit, whatever the chunk size (a chunk of one pair, chunks
that start on and off segment starts, one chunk for all).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import evdown_torch.transforms.functional.estimation.cubic as cubic_module
from evdown_torch import CubicEstimation, eager_kernels
from tests.helpers import argument_spy, random_stream

SENSOR = (20, 12, 2)


def captured_sums_inputs(arr, monkeypatch, **settings) -> list[tuple]:
    """The arguments of every ``_mid_segment_sums`` call of one CubicEstimation call (on the
    eager path, whose solver this is)."""
    real = cubic_module._mid_segment_sums
    calls = argument_spy(monkeypatch, cubic_module, "_mid_segment_sums")
    with eager_kernels():
        CubicEstimation(SENSOR, factor=(3, 2), threshold=0.2, **settings)(arr)
    monkeypatch.setattr(cubic_module, "_mid_segment_sums", real)
    return calls


@pytest.mark.parametrize("max_delay", [None, 150])
@pytest.mark.parametrize("float_time", [False, True])
def test_mid_segment_sums_do_not_depend_on_the_chunk_size(rng, monkeypatch, max_delay, float_time):
    arr = random_stream(rng, 1500, SENSOR, t_max=4000)
    if float_time:
        timed = np.empty(arr.shape, dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<f8"), ("p", "<i8")])
        for name in ("x", "y", "p"):
            timed[name] = arr[name]
        timed["t"] = arr["t"] * 1.37
        arr = timed
    calls = captured_sums_inputs(arr, monkeypatch, max_delay=max_delay)
    assert calls
    for args in calls:
        monkeypatch.setattr(cubic_module, "CHUNK", 1 << 30)
        value, slope = cubic_module._mid_segment_sums(*args)
        assert bool((value != 0).any())
        for chunk in (1, 2, 3, 7, 64):
            monkeypatch.setattr(cubic_module, "CHUNK", chunk)
            got_value, got_slope = cubic_module._mid_segment_sums(*args)
            assert torch.equal(got_value, value) and torch.equal(got_slope, slope)
            assert torch.equal(got_value.signbit(), value.signbit())
