"""Tonic's RefractoryPeriod and Decimation as peers: Tonic's results (against a per-event loop
of each rule and Tonic's own transforms), then Downsample; budgets on real N-MNIST."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch.data.sources import NMNISTSource
from evdown_torch.transforms import Downsample, TonicDecimation, TonicRefractoryPeriod
from evdown_torch.transforms.calibrate import BudgetTarget, calibration
from evdown_torch.transforms.registry import make_method
from tests.conftest import SHARED_DATA
from tests.helpers import random_stream

tonic = pytest.importorskip("tonic")

SENSOR = (9, 7, 2)


def refractory_reference(arr: np.ndarray, delta: float) -> list[bool]:
    """Keep iff more than ``delta`` since the pixel's previous event (kept or not)."""
    last: dict[tuple[int, int], float] = {}
    keep = []
    for e in arr:
        pixel = (int(e["x"]), int(e["y"]))
        keep.append(float(e["t"]) - last.get(pixel, -delta) > delta)
        last[pixel] = float(e["t"])
    return keep


def decimation_reference(arr: np.ndarray, n: int) -> list[bool]:
    """Keep each pixel's n-th, 2n-th, ... event."""
    seen: dict[tuple[int, int], int] = {}
    keep = []
    for e in arr:
        pixel = (int(e["x"]), int(e["y"]))
        seen[pixel] = seen.get(pixel, 0) + 1
        keep.append(seen[pixel] % n == 0)
    return keep


def _downsampled(arr: np.ndarray, keep, factor: int) -> list[tuple]:
    return [(int(e["x"]) // factor, int(e["y"]) // factor, int(e["t"]), bool(e["p"]))
            for e, k in zip(arr, keep, strict=True) if k]


def _rows(out: np.ndarray) -> list[tuple]:
    return [(int(e["x"]), int(e["y"]), int(e["t"]), bool(e["p"])) for e in out]


@pytest.mark.parametrize("seed", range(4))
def test_refractory_period_is_its_rule_then_downsample(seed):
    rng = np.random.default_rng(seed)
    arr = random_stream(rng, 300, SENSOR, t_max=2_000)
    arr["t"] += 1  # Tonic drops a pixel's first event at t <= 0 (its memory starts at -delta)
    delta = [5.0, 40.0, 130.0, 1.0][seed]
    out = TonicRefractoryPeriod(SENSOR, 2, delta=delta)(arr)
    assert _rows(out) == _downsampled(arr, refractory_reference(arr, delta), 2)
    tonic_first = tonic.transforms.RefractoryPeriod(delta=delta)(arr)
    np.testing.assert_array_equal(out, Downsample(SENSOR, 2)(tonic_first))


@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_decimation_is_its_rule_then_downsample(n, rng):
    arr = random_stream(rng, 300, SENSOR, t_max=2_000)
    out = TonicDecimation(SENSOR, 3, n=n)(arr)
    assert _rows(out) == _downsampled(arr, decimation_reference(arr, n), 3)
    tonic_first = tonic.transforms.Decimation(n=n)(arr)
    expected = Downsample(SENSOR, 3)(tonic_first) if len(tonic_first) else arr[:0]
    np.testing.assert_array_equal(out, expected)


def test_unsorted_input_is_taken_in_time_order_and_every_container_works(rng):
    arr = random_stream(rng, 200, SENSOR, t_max=500)
    shuffled = arr[rng.permutation(len(arr))]
    for transform in (TonicRefractoryPeriod(SENSOR, 2, delta=20), TonicDecimation(SENSOR, 2, n=3)):
        expected = transform(arr)
        in_order = shuffled[np.argsort(shuffled["t"], kind="stable")]
        np.testing.assert_array_equal(transform(shuffled), transform(in_order))
        tensor = torch.tensor(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], 1)
                              .astype(np.int64))
        np.testing.assert_array_equal(
            transform(tensor).numpy(),
            np.stack([expected["x"], expected["y"], expected["t"], expected["p"]], 1))
        assert len(transform(arr[:0])) == 0
        batch = transform.batch([arr, arr[:0], arr[:50]])
        for got, one in zip(batch, [arr, arr[:0], arr[:50]], strict=True):
            np.testing.assert_array_equal(got, transform(one))


def test_no_session_and_checked_settings():
    with pytest.raises(NotImplementedError, match="no streaming session"):
        TonicRefractoryPeriod(SENSOR, 2).session()
    with pytest.raises(NotImplementedError, match="no streaming session"):
        TonicDecimation(SENSOR, 2).session()
    with pytest.raises(ValueError, match="delta must be a positive"):
        TonicRefractoryPeriod(SENSOR, 2, delta=0)
    with pytest.raises(ValueError, match="n must be at least 1"):
        TonicDecimation(SENSOR, 2, n=0.2)
    assert TonicDecimation(SENSOR, 2, n=3.4).n == 3
    assert make_method("decimation", SENSOR, 2, n=5).n == 5
    assert make_method("refractory", SENSOR, 2, delta=50).delta == 50.0


@pytest.fixture(scope="module")
def recordings():
    root = SHARED_DATA / "nmnist_small"
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    torch.set_num_threads(1)
    source = NMNISTSource(root, split="train")
    chosen = [source.labels.index(d) for d in range(10)]  # Tonic's loops are slow: 10
    return [source.load(i)[0] for i in chosen]


def test_refractory_budget_on_real_recordings(recordings):
    inputs = sum(len(r) for r in recordings)
    totals = [sum(len(o) for o in TonicRefractoryPeriod((34, 34, 2), 2, delta=d).batch(recordings))
              for d in (100.0, 1_000.0, 10_000.0, 100_000.0)]
    assert totals == sorted(totals, reverse=True) and totals[-1] < 0.2 * inputs
    for ratio in (0.25, 0.1):
        found = calibration(TonicRefractoryPeriod((34, 34, 2), 4), recordings,
                            BudgetTarget.ratio(ratio))
        assert abs(found.count - ratio * inputs) <= 0.05 * ratio * inputs


def test_decimation_takes_the_closest_budget_it_can(recordings):
    inputs = sum(len(r) for r in recordings)
    counts = {n: sum(len(o) for o in TonicDecimation((34, 34, 2), 2, n=n).batch(recordings))
              for n in range(1, 9)}
    assert list(counts.values()) == sorted(counts.values(), reverse=True)
    found = calibration(TonicDecimation((34, 34, 2), 2), recordings, BudgetTarget.ratio(0.25))
    best = min(counts.values(), key=lambda c: abs(c - 0.25 * inputs))
    assert found.count == best and found.transform.n == next(
        n for n, c in counts.items() if c == best)
