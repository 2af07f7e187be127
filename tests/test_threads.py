"""torch_threads sets torch's thread count for a block only; library calls leave it alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch.threads import torch_threads


def test_the_count_is_restored_even_after_an_error():
    before = torch.get_num_threads()
    with pytest.raises(RuntimeError), torch_threads(1):
        assert torch.get_num_threads() == 1
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError, match="threads must be a positive integer"), torch_threads(0):
        pass


def test_realtime_replay_leaves_the_callers_thread_count(rng):
    from evdown_torch.bench.realtime import realtime_benchmark
    from tests.helpers import random_stream

    events = np.sort(random_stream(rng, 300, (16, 16, 2), t_max=20_000), order="t")
    before = torch.get_num_threads()
    with torch_threads(2):  # a setting of the caller's that is not 1
        realtime_benchmark(events, (16, 16, 2), factor=2, methods=["downsample"],
                           chunks_us=(5000,),
                           rates=(None,), max_chunks=2)
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before
