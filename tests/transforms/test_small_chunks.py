"""A live stream's small chunks: their fixed cost follows the chunk, not the sensor's regions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch import EventCount
from evdown_torch.transforms.functional.reference import region_runs
from tests.helpers import random_stream


def slow_runs(region: list[int]) -> tuple[list[int], list[int], list[int], list[bool]]:
    touched, firsts, lasts = [], [], []
    for i, r in enumerate(region):
        if i == 0 or r != region[i - 1]:
            touched.append(r)
            firsts.append(i)
            lasts.append(i)
        else:
            lasts[-1] = i
    return touched, firsts, lasts, [i in firsts for i in range(len(region))]


@pytest.mark.parametrize(("n", "regions"), [(0, 4), (1, 1024), (5, 1024), (3000, 64),
                                            (64, 64), (63, 64)])
def test_region_runs_by_starts_and_by_bisection_agree_with_a_slow_count(n, regions, rng):
    region = np.sort(rng.integers(0, regions, n)).astype(np.int16)
    runs = region_runs(torch.from_numpy(region), regions)
    assert runs.touched.dtype == runs.firsts.dtype == runs.lasts.dtype == torch.int64
    assert tuple(v.tolist() for v in runs) == slow_runs(region.tolist())


@pytest.mark.usefixtures("eager")  # the eager kernel's own work (the compiled loop has none)
def test_a_one_event_chunk_builds_no_index_of_every_region(monkeypatch, rng):
    sensor = (256, 256, 2)  # 4,096 regions at factor 4
    events = random_stream(rng, 60, sensor, t_max=10_000)
    down = EventCount(sensor, factor=4, threshold=0.5)
    session = down.session()
    warm = [session(events[i:i + 1]) for i in range(10)]
    sizes: list[int] = []
    real = torch.arange

    def arange(*args, **kwargs):
        out = real(*args, **kwargs)
        sizes.append(out.shape[0])
        return out

    monkeypatch.setattr(torch, "arange", arange)
    rest = [session(events[i:i + 1]) for i in range(10, len(events))]
    monkeypatch.undo()
    assert sizes and max(sizes) < 64 * 64  # per-event work only, after the first chunk
    assert np.array_equal(np.concatenate(warm + rest + [session.flush()]), down(events))
