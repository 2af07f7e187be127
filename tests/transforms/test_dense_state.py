"""Methods with a value for every pixel or region refuse a sensor whose state would not fit,
up front, with the memory it needs and the largest sensor that fits; the rest are unaffected.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from evdown_torch import (
    CubicEstimation,
    Downsample,
    EventCount,
    LIFPooling,
    LinearEstimation,
    PhotocurrentPooling,
)
from tests.helpers import DVS_DTYPE

HUGE = (65535, 65535, 2)


def _events(sensor, n=200, seed=0) -> np.ndarray:
    generator = np.random.default_rng(seed)
    ev = np.zeros(n, DVS_DTYPE)
    ev["x"] = generator.integers(0, min(sensor[0], 32767), n)
    ev["y"] = generator.integers(0, min(sensor[1], 32767), n)
    ev["p"], ev["t"] = generator.random(n) < 0.5, np.sort(generator.integers(0, 10**6, n))
    return ev


#: Each way a method builds its dense state, and the bytes it keeps per pixel and per region.
DENSE = {
    "event_count": (lambda s, ev: EventCount(s, 1)(ev), 0, 16),
    "event_count_batch": (lambda s, ev: EventCount(s, 1).batch([ev, ev]), 0, 32),
    "event_count_session": (lambda s, ev: EventCount(s, 1).session()(ev), 0, 16),
    "linear_session": (lambda s, ev: LinearEstimation(s, 1, max_delay=10).session()(ev), 8, 8),
    "cubic_session": (lambda s, ev: CubicEstimation(s, 1, max_delay=10).session()(ev), 8, 8),
    "lif_session": (lambda s, ev: LIFPooling(s, 1).session()(ev), 0, 16),
    "photocurrent": (lambda s, ev: PhotocurrentPooling(s, 1)(ev), 8, 8),
    "photocurrent_batch": (lambda s, ev: PhotocurrentPooling(s, 1).batch([ev, ev]), 16, 16),
    "photocurrent_session": (lambda s, ev: PhotocurrentPooling(s, 1).session()(ev), 8, 8),
    "frames": (lambda s, ev: PhotocurrentPooling(s, 1, fps=100.0)(ev), 16, 16),
    "frames_session": (lambda s, ev: PhotocurrentPooling(s, 1, fps=100.0).session()(ev),
                       16, 16),
}


@pytest.mark.parametrize("name", sorted(DENSE))
def test_a_huge_sensor_is_refused_with_what_it_needs_before_any_allocation(name, monkeypatch):
    # 8 GB of memory, whatever the machine: a quarter of it is 2 GB.
    monkeypatch.setattr("evdown_torch.checks.device_memory", lambda device=None: 8 * 10**9,
                        raising=False)
    run, pixel_bytes, region_bytes = DENSE[name]
    need = (pixel_bytes + region_bytes) * HUGE[0] * HUGE[1]  # factor 1: a region per pixel
    side = int(HUGE[0] * (2e9 / need) ** 0.5)  # the same shape at 2 GB
    with pytest.raises(ValueError) as error:
        run(HUGE, _events(HUGE))
    message = str(error.value)
    assert "keeps state for every pixel or region of its sensor: 65535 x 65535 pixels" in message
    assert f"need {need / 1e9:.3g} GB" in message and "quarter of the 8 GB" in message
    assert f"the largest sensor of this shape that fits is about {side} x {side}" in message


@pytest.mark.parametrize("name", sorted(DENSE))
def test_the_largest_sensor_said_to_fit_runs_and_a_larger_one_is_refused(name, monkeypatch):
    monkeypatch.setattr("evdown_torch.checks.device_memory", lambda device=None: 2**25,
                        raising=False)
    run = DENSE[name][0]
    with pytest.raises(ValueError, match="largest sensor") as error:
        run((4000, 3000, 2), _events((4000, 3000, 2)))
    width, height = map(int, re.search(r"about (\d+) x (\d+) pixels", str(error.value)).groups())
    assert abs(width / height - 4 / 3) < 0.01  # the same shape
    run((width, height, 2), _events((width, height, 2)))  # 8 MB of state: runs
    with pytest.raises(ValueError, match="largest sensor"):
        run((width * 11 // 10, height * 11 // 10, 2), _events((width, height, 2)))


def test_long_thin_sensors_and_the_sparse_methods_are_unaffected():
    long_thin = (65535, 2, 2)  # the sensor that works
    ev = _events(long_thin)
    for run, *_ in DENSE.values():
        run(long_thin, ev)
    out = Downsample(HUGE, 1)(_events(HUGE))  # no per-pixel state
    assert len(out) == 200
    assert len(LinearEstimation(HUGE, 1)(_events(HUGE))) > 0  # whole-stream: sparse
